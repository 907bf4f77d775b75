#include <pcl_animseg/progress.h>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iostream>
#include <sstream>
#include <vector>

namespace pcl_animseg {

double peakResidentMiB() {
  struct rusage usage;
  if (getrusage(RUSAGE_SELF, &usage) != 0) return 0.0;
  return static_cast<double>(usage.ru_maxrss) / 1024.0;  // ru_maxrss is in KiB on Linux
}

namespace {

// The first `count` numbers of a /proc/stat text's "cpu" line (the sum over the CPUs, not cpu0,
// cpu1 ..): user nice system idle iowait irq softirq steal (guest guest_nice), counts of clock
// ticks. False where the text has no such line or fewer numbers.
bool cpuLineTicks(const std::string& proc_stat, int count, std::vector<unsigned long long>& ticks) {
  std::istringstream in(proc_stat);
  std::string line;
  while (std::getline(in, line)) {
    std::istringstream fields(line);
    std::string name;
    if (!(fields >> name) || name != "cpu") continue;
    ticks.clear();
    for (int k = 0; k < count; ++k) {
      std::string word;
      if (!(fields >> word) || word.empty() ||
          word.find_first_not_of("0123456789") != std::string::npos)
        return false;
      ticks.push_back(std::strtoull(word.c_str(), nullptr, 10));
    }
    return true;
  }
  return false;
}

// How much a count that only grows grew from `before` to `after`: at least 0; negative where either
// is unknown (negative).
double growth(double before, double after) {
  return before < 0.0 || after < 0.0 ? -1.0 : std::max(0.0, after - before);
}

// /proc/stat's first line (the "cpu" line comes first); empty where it cannot be read.
std::string procStatHead() {
  std::ifstream in("/proc/stat");
  std::string head;
  if (!in || !std::getline(in, head)) return std::string();
  return head;
}

}  // namespace

double parseCpuSteal(const std::string& proc_stat, double ticks_per_second) {
  std::vector<unsigned long long> t;
  if (!cpuLineTicks(proc_stat, 8, t) || !(ticks_per_second > 0.0)) return -1.0;
  return static_cast<double>(t[7]) / ticks_per_second;
}

double cpuStealSeconds() {
  return parseCpuSteal(procStatHead(), static_cast<double>(sysconf(_SC_CLK_TCK)));
}

double cpuStealSince(double before) { return growth(before, cpuStealSeconds()); }

int onlineCpus() {
  const long n = sysconf(_SC_NPROCESSORS_ONLN);
  return n > 0 ? static_cast<int>(n) : 1;
}

std::string hostStealNote(double steal, double seconds, int cpus) {
  if (!(steal >= 0.05) || !(seconds > 0.0) || cpus < 1) return std::string();
  const double share = steal / (seconds * cpus);
  if (!(share > 0.02)) return std::string();
  char text[256];
  std::snprintf(text, sizeof(text),
                "the machine's host took %.1f%% of its CPUs' time during the run (%.2f CPU "
                "seconds of steal): the timings are slower than this machine's own",
                100.0 * share, steal);
  return text;
}

double parseCpuBusy(const std::string& proc_stat, double ticks_per_second) {
  // The busy ones: user, nice, system, irq and softirq.
  std::vector<unsigned long long> t;
  if (!cpuLineTicks(proc_stat, 7, t) || !(ticks_per_second > 0.0)) return -1.0;
  return static_cast<double>(t[0] + t[1] + t[2] + t[5] + t[6]) / ticks_per_second;
}

double processCpuSeconds() {
  struct rusage usage;
  if (getrusage(RUSAGE_SELF, &usage) != 0) return -1.0;
  auto sec = [](const timeval& tv) { return static_cast<double>(tv.tv_sec) + 1e-6 * tv.tv_usec; };
  return sec(usage.ru_utime) + sec(usage.ru_stime);
}

CpuReading readCpu() {
  CpuReading r;
  const std::string head = procStatHead();
  const double ticks = static_cast<double>(sysconf(_SC_CLK_TCK));
  r.machine_busy = parseCpuBusy(head, ticks);
  r.steal = parseCpuSteal(head, ticks);
  r.own = processCpuSeconds();
  return r;
}

double otherProgramsCpuBetween(const CpuReading& before, const CpuReading& after) {
  if (before.machine_busy < 0.0 || before.own < 0.0 || after.machine_busy < 0.0 || after.own < 0.0)
    return -1.0;
  // The machine's count is in clock ticks and this process's exact: a little of either's
  // rounding is left, never a negative share.
  return std::max(0.0, (after.machine_busy - before.machine_busy) - (after.own - before.own));
}

double otherProgramsCpuSince(const CpuReading& before) {
  return otherProgramsCpuBetween(before, readCpu());
}

double cpuStealBetween(const CpuReading& before, const CpuReading& after) {
  return growth(before.steal, after.steal);
}

std::string otherProgramsNote(double other, double seconds, int cpus, int threads) {
  if (!(other >= 0.2) || !(seconds > 0.0) || cpus < 1) return std::string();
  const double share = other / (seconds * cpus);
  if (!(share >= 0.10)) return std::string();
  // Only where the run's threads and the others' (on average) wanted more CPUs than there are:
  // runs given their share (two of 16 threads on 32 CPUs) wait for nothing of each other's.
  if (!(other / seconds > static_cast<double>(cpus - std::max(threads, 0)))) return std::string();
  char text[512];
  std::snprintf(text, sizeof(text),
                "other programs used %.0f%% of the CPUs' time during the run (%.1f CPU seconds): "
                "this run's %d threads shared %d CPUs with them, and OpenMP threads that spin "
                "while they wait slow runs side by side down many times over; give each run its "
                "share of the CPUs (--threads, or taskset), or set OMP_WAIT_POLICY=passive",
                100.0 * share, other, threads, cpus);
  return text;
}

Progress::Progress(bool quiet, bool verbose)
    : quiet_(quiet),
      verbose_(verbose && !quiet),
      tty_(isatty(STDERR_FILENO) != 0),
      start_(Clock::now()) {}

double Progress::elapsed() const {
  return std::chrono::duration<double>(Clock::now() - start_).count();
}

void Progress::begin(const std::string& stage, std::size_t total) {
  Stage s;
  s.name = open_.empty() ? stage : open_.back().name + "/" + stage;
  s.total = total;
  s.start = Clock::now();
  open_.push_back(s);
  if (!quiet_) std::cerr << "[" << s.name << "] started" << std::endl;
}

void Progress::update(std::size_t done) {
  if (quiet_ || open_.empty() || open_.back().total == 0) return;
  Stage& s = open_.back();
  const double frac = std::min(1.0, static_cast<double>(done) / static_cast<double>(s.total));
  const double secs = std::chrono::duration<double>(Clock::now() - s.start).count();
  if (tty_) {
    // A bar that rewrites itself; at most 100 redraws per stage.
    const int pct = static_cast<int>(frac * 100.0);
    if (pct == s.last_shown) return;
    s.last_shown = pct;
    const int width = 30;
    const int fill = static_cast<int>(frac * width);
    std::fprintf(stderr, "\r[%s] |%s%s| %zu/%zu %.1fs", s.name.c_str(),
                 std::string(fill, '#').c_str(), std::string(width - fill, ' ').c_str(), done,
                 s.total, secs);
    std::fflush(stderr);
  } else {
    // Plain lines for logs: at most one per 10%.
    const int decile = static_cast<int>(frac * 10.0);
    if (decile == s.last_shown) return;
    s.last_shown = decile;
    std::fprintf(stderr, "[%s] %zu/%zu (%d%%) %.1fs\n", s.name.c_str(), done, s.total, decile * 10,
                 secs);
  }
}

double Progress::end(const std::string& detail) {
  if (open_.empty()) return 0.0;
  const Stage s = open_.back();
  open_.pop_back();
  const double secs = std::chrono::duration<double>(Clock::now() - s.start).count();
  // A stage run again (features in blocks of frames) adds to its first record.
  auto same = std::find_if(timings_.begin(), timings_.end(),
                           [&](const auto& rec) { return rec.first == s.name; });
  if (same != timings_.end())
    same->second += secs;
  else
    timings_.emplace_back(s.name, secs);
  if (!quiet_) {
    if (tty_ && s.total > 0 && s.last_shown >= 0) std::cerr << "\n";
    std::ostringstream os;
    os.setf(std::ios::fixed);
    os.precision(3);
    os << "[" << s.name << "] done in " << secs << " s";
    if (!detail.empty()) os << " (" << detail << ")";
    if (verbose_) {
      os.precision(0);
      os << ", peak RSS " << peakResidentMiB() << " MiB";
    }
    std::cerr << os.str() << std::endl;
  }
  return secs;
}

void Progress::abandon(std::size_t depth) {
  while (open_.size() > depth) {
    const Stage s = open_.back();
    open_.pop_back();
    if (!quiet_) {
      if (tty_ && s.total > 0 && s.last_shown >= 0) std::cerr << "\n";
      std::cerr << "[" << s.name << "] abandoned" << std::endl;
    }
  }
}

void Progress::info(const std::string& message) const {
  if (!quiet_) std::cerr << message << std::endl;
}

void Progress::debug(const std::string& message) const {
  if (verbose_) std::cerr << message << std::endl;
}

}  // namespace pcl_animseg
