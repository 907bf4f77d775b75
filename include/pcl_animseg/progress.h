#pragma once
/** \file progress.h Per-stage progress and timing on stderr (silenced by --quiet). */
#include <chrono>
#include <cstddef>
#include <string>
#include <utility>
#include <vector>

namespace pcl_animseg {

/** \brief Records how long each stage took and reports progress on stderr.
 *
 * On a terminal, counts are shown as an updating bar; otherwise as plain lines (at most one per
 * 10% of the work), so logs stay readable. Nothing is printed when quiet.
 */
class Progress {
 public:
  explicit Progress(bool quiet = false, bool verbose = false);

  /** \brief Start a named stage (ends the previous one if still open). */
  void begin(const std::string& stage, std::size_t total = 0);
  /** \brief Report that `done` of the stage's `total` units are finished. Thread-safe enough to
   * call from one thread inside an OpenMP loop (call it from thread 0). */
  void update(std::size_t done);
  /** \brief End the current stage; its time is recorded under its name. */
  double end(const std::string& detail = "");
  /** \brief A line of information (not printed when quiet). */
  void info(const std::string& message) const;
  /** \brief A line only shown with --verbose. */
  void debug(const std::string& message) const;

  bool quiet() const { return quiet_; }
  bool verbose() const { return verbose_; }
  /** \brief (stage, seconds) in the order the stages ran. */
  const std::vector<std::pair<std::string, double>>& timings() const { return timings_; }
  /** \brief Seconds since this object was made. */
  double elapsed() const;

 private:
  using Clock = std::chrono::steady_clock;
  bool quiet_;
  bool verbose_;
  bool tty_;
  std::string stage_;
  std::size_t total_ = 0;
  int last_decile_ = -1;
  Clock::time_point start_;
  Clock::time_point stage_start_;
  bool open_ = false;
  std::vector<std::pair<std::string, double>> timings_;
};

}  // namespace pcl_animseg
