#include <pcl_animseg/progress.h>

#include <unistd.h>

#include <cstdio>
#include <iostream>
#include <sstream>

namespace pcl_animseg {

Progress::Progress(bool quiet, bool verbose)
    : quiet_(quiet),
      verbose_(verbose && !quiet),
      tty_(isatty(STDERR_FILENO) != 0),
      start_(Clock::now()),
      stage_start_(start_) {}

double Progress::elapsed() const {
  return std::chrono::duration<double>(Clock::now() - start_).count();
}

void Progress::begin(const std::string& stage, std::size_t total) {
  if (open_) end();
  stage_ = stage;
  total_ = total;
  last_decile_ = -1;
  open_ = true;
  stage_start_ = Clock::now();
  if (!quiet_) std::cerr << "[" << stage_ << "] started" << std::endl;
}

void Progress::update(std::size_t done) {
  if (quiet_ || !open_ || total_ == 0) return;
  const double frac = std::min(1.0, static_cast<double>(done) / static_cast<double>(total_));
  const int decile = static_cast<int>(frac * 10.0);
  const double secs = std::chrono::duration<double>(Clock::now() - stage_start_).count();
  if (tty_) {
    // A bar that rewrites itself; at most 100 redraws per stage.
    const int pct = static_cast<int>(frac * 100.0);
    if (pct == last_decile_) return;
    last_decile_ = pct;
    const int width = 30;
    const int fill = static_cast<int>(frac * width);
    std::fprintf(stderr, "\r[%s] |%s%s| %zu/%zu %.1fs", stage_.c_str(), std::string(fill, '#').c_str(),
                 std::string(width - fill, ' ').c_str(), done, total_, secs);
    std::fflush(stderr);
  } else {
    if (decile == last_decile_) return;
    last_decile_ = decile;
    std::fprintf(stderr, "[%s] %zu/%zu (%d%%) %.1fs\n", stage_.c_str(), done, total_, decile * 10, secs);
  }
}

double Progress::end(const std::string& detail) {
  if (!open_) return 0.0;
  const double secs = std::chrono::duration<double>(Clock::now() - stage_start_).count();
  timings_.emplace_back(stage_, secs);
  open_ = false;
  if (!quiet_) {
    if (tty_ && total_ > 0) std::cerr << "\n";
    std::ostringstream os;
    os.setf(std::ios::fixed);
    os.precision(3);
    os << "[" << stage_ << "] done in " << secs << " s";
    if (!detail.empty()) os << " (" << detail << ")";
    std::cerr << os.str() << std::endl;
  }
  return secs;
}

void Progress::info(const std::string& message) const {
  if (!quiet_) std::cerr << message << std::endl;
}

void Progress::debug(const std::string& message) const {
  if (verbose_) std::cerr << message << std::endl;
}

}  // namespace pcl_animseg
