#pragma once
/** \file progress.h Per-stage progress and timing on stderr (silenced by --quiet). */
#include <chrono>
#include <cstddef>
#include <string>
#include <utility>
#include <vector>

namespace pcl_animseg {

/** \brief Peak resident memory of this process so far, in MiB (0 where the OS cannot say). */
double peakResidentMiB();

/** \brief CPU time that the machine's host gave to other work while this machine's CPUs had work
 * to do ("steal" on the "cpu" line of Linux's /proc/stat: the hypervisor of a virtual machine ran
 * something else on them), summed over the CPUs, in seconds since boot; negative where the OS
 * does not say (not Linux, or a kernel that does not count it). The difference over a run is how
 * much CPU time its timings waited for: on a busy host, a run of 16 threads whose barriers wait
 * for a CPU that was taken away. */
double cpuStealSeconds();

/** \brief The steal since `before` (a cpuStealSeconds() reading): the CPU time the host took over
 * a run, at least 0; negative where either reading is unknown. */
double cpuStealSince(double before);

/** \brief The steal of a /proc/stat text (the 8th number of its "cpu" line) in seconds, at
 * `ticks_per_second` clock ticks a second; negative where the text has no such number. */
double parseCpuSteal(const std::string& proc_stat, double ticks_per_second);

/** \brief The CPUs online (at least 1). */
int onlineCpus();

/** \brief A note for a run's summary when the host took a notable share of the CPUs' time while
 * it ran: `steal` CPU seconds over `seconds` of `cpus` CPUs, more than 2% of their time and at
 * least 0.05 CPU seconds (5 clock ticks: one tick over a short run is not a share); empty
 * otherwise, and where the steal is unknown (negative). */
std::string hostStealNote(double steal, double seconds, int cpus);

/** \brief The busy time of a /proc/stat text's "cpu" line (user, nice, system, irq and softirq:
 * its 1st, 2nd, 3rd, 6th and 7th numbers; not idle, iowait or steal) in seconds, at
 * `ticks_per_second` clock ticks a second; negative where the text has no such line. */
double parseCpuBusy(const std::string& proc_stat, double ticks_per_second);

/** \brief This process's CPU time so far (all its threads, user and system), in seconds;
 * negative where the OS does not say. */
double processCpuSeconds();

/** \brief Readings at one moment: the machine's busy time (its CPUs' summed, since boot), this
 * process's CPU time and the host's steal (seconds; negative where unknown). */
struct CpuReading {
  double machine_busy = -1.0;
  double own = -1.0;
  double steal = -1.0;
};

/** \brief The machine's busy time and cpuStealSeconds() from one reading of /proc/stat, and
 * processCpuSeconds(), now. */
CpuReading readCpu();

/** \brief The CPU time the machine's other programs used between two readings: its CPUs' busy
 * time less this process's own, at least 0; negative where a reading is unknown. */
double otherProgramsCpuBetween(const CpuReading& before, const CpuReading& after);

/** \brief otherProgramsCpuBetween(before, readCpu()). */
double otherProgramsCpuSince(const CpuReading& before);

/** \brief The host's steal between two readings (cpuStealSince's), at least 0; negative where a
 * reading is unknown. */
double cpuStealBetween(const CpuReading& before, const CpuReading& after);

/** \brief A note for a run's summary when other programs used a notable share of the machine's
 * CPUs while it ran and the run's `threads` OpenMP threads did not fit beside them: `other` CPU
 * seconds over `seconds` of `cpus` CPUs, at least 10% of their time and 0.2 CPU seconds, and more
 * CPUs busy on average than the `cpus - threads` the run left; it says what that does and what
 * to do about it. Empty otherwise, and where `other` is unknown (negative). */
std::string otherProgramsNote(double other, double seconds, int cpus, int threads);

/** \brief Records how long each stage took and reports progress on stderr.
 *
 * On a terminal, counts are shown as an updating bar; otherwise as plain lines (at most one per
 * 10% of the work), so logs stay readable. Nothing is printed when quiet. With verbose, each
 * stage's "done" line also gives the process's peak resident memory so far.
 */
class Progress {
 public:
  explicit Progress(bool quiet = false, bool verbose = false);

  /** \brief Start a named stage. A stage begun while another is open is its sub-stage: its time
   * is recorded as "parent/stage" and the parent keeps running (a library stage may report its
   * own steps inside the caller's stage). */
  void begin(const std::string& stage, std::size_t total = 0);
  /** \brief Report that `done` of the stage's `total` units are finished. Thread-safe enough to
   * call from one thread inside an OpenMP loop (call it from thread 0). */
  void update(std::size_t done);
  /** \brief End the innermost open stage; its time is recorded under its (prefixed) name. */
  double end(const std::string& detail = "");
  /** \brief How many stages are open (sub-stages included). */
  std::size_t depth() const { return open_.size(); }
  /** \brief Closes the stages opened beyond `depth` without recording their times: work thrown
   * away (a device stage that failed and runs again on the CPU), so that the stage run again is
   * recorded under its own name, not as a sub-stage of the abandoned one. */
  void abandon(std::size_t depth);
  /** \brief A line of information (not printed when quiet). */
  void info(const std::string& message) const;
  /** \brief A line only shown with --verbose. */
  void debug(const std::string& message) const;

  bool quiet() const { return quiet_; }
  bool verbose() const { return verbose_; }
  /** \brief (stage, seconds) in the order the stages first ran; a stage run several times
   * under one name is one record with the sum of its times. */
  const std::vector<std::pair<std::string, double>>& timings() const { return timings_; }
  /** \brief Seconds since this object was made. */
  double elapsed() const;

 private:
  using Clock = std::chrono::steady_clock;
  bool quiet_;
  bool verbose_;
  bool tty_;
  struct Stage {
    std::string name;  ///< full name, "parent/child" for sub-stages
    std::size_t total = 0;
    int last_shown = -1;
    Clock::time_point start;
  };
  Clock::time_point start_;
  std::vector<Stage> open_;
  std::vector<std::pair<std::string, double>> timings_;
};

}  // namespace pcl_animseg
