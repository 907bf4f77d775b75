#pragma once
/** \file chained_fit.h Per-frame fits chained along a sequence, with the frames in parallel. */
#include <omp.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/segmentation/score_fit.h>

#include <algorithm>
#include <chrono>
#include <cstddef>
#include <functional>
#include <limits>
#include <string>
#include <tuple>
#include <utility>
#include <vector>

namespace pcl_animseg {
namespace segmentation {

namespace detail {
/** \brief f(j) for every j < n: side by side where that can help (n > 1, outside a parallel
 * region; OpenMP's dynamic schedule in chunks of `chunk`), else in the caller's thread without
 * calling into the OpenMP runtime (a parallel loop whose `if` fails is still a team of one that it
 * starts: about 5000 a run at 800k on the GPU, 1 us each). Each j writes its own results, so the
 * results are the same either way. */
template <class F>
void eachIndex(long n, int chunk, F&& f) {
  if (n > 1 && !omp_in_parallel()) {
#pragma omp parallel for schedule(dynamic, chunk)
    for (long j = 0; j < n; ++j) f(j);
  } else {
    for (long j = 0; j < n; ++j) f(j);
  }
}
}  // namespace detail

/** \brief One start of a frame's fit, and whether it depends on the fits of earlier frames. */
template <class Pose>
struct ChainStart {
  Pose pose;
  bool chained = false;
};

/** \brief Where a frame's chained starts come from: the frame it is fitted after (`before`; -1
 * for the reference) and the frame before that (`two_before`: with `before`, a constant-velocity
 * guess; -1: none). */
struct ChainStep {
  int before = -1, two_before = -1;
};

/** \brief The frames of a chain away from a reference frame: `order`, a serial run's (each frame
 * after the one it is fitted after; forwards first, then backwards), and each frame's step.
 *
 * A chain of small fits drifts: what a fit hardly constrains moves a little at every step, and
 * the drift adds up with the steps (the motion method's samples on a 160-frame humanoid: a mean
 * ICP residual of 0.40 spacings in the frames where a 48-frame one of the same motion has 0.28).
 * So a side of the reference longer than `max_steps` frames (kMaxChainSteps unless a caller
 * asks for shorter chains) goes through key frames `stride` apart (each fitted after the key
 * frame before it), and each frame between after the frame before it, back to a key frame: no
 * frame is more than about max_steps + stride steps from the reference, and a chain's fits need
 * about as many rounds. A side of at most max_steps frames is one chain of single steps. The stride
 * is at most kMaxStride: a key frame's step is that many frames' motion, and the tracking holds
 * steps of about 50 degrees at a joint (generated gallops in 20 frames), while a capture at 30
 * frames a second moves a fast limb up to about 10 degrees a frame; longer sides get longer chains
 * of key frames instead. */
struct ChainFrames {
  std::vector<int> order;
  std::vector<ChainStep> step;  ///< per frame (the reference's: none)
};
constexpr int kMaxChainSteps = 48;
constexpr int kMaxStride = 4;
inline ChainFrames chainFrames(int T, int ref, int max_steps = kMaxChainSteps) {
  max_steps = std::max(1, max_steps);
  ChainFrames c;
  c.step.assign(static_cast<std::size_t>(T > 0 ? T : 0), ChainStep());
  for (int dir : {+1, -1}) {
    const int n = dir > 0 ? T - 1 - ref : ref;
    if (n <= 0) continue;
    const int stride = std::clamp((n + max_steps - 1) / max_steps, 1, kMaxStride);
    for (int d = 1; d <= n; ++d) {
      const int t = ref + dir * d, r = d % stride;
      c.order.push_back(t);
      ChainStep& st = c.step[t];
      if (r == 0) {  // a key frame (every frame when the stride is 1)
        st.before = t - dir * stride;
        if (d >= 2 * stride) st.two_before = t - 2 * dir * stride;
      } else {  // between key frames: after the frame before, the same step as it took
        st.before = t - dir;
        if (r >= 2) st.two_before = t - 2 * dir;
      }
    }
  }
  return c;
}

/** \brief A fit that fitChainsBatched asks for: frame `frame` of chain `chain` from `start`, which
 * scored `score`. */
template <class Pose>
struct ChainFit {
  int chain = 0, frame = 0;
  Pose start;
  double score = 0.0;
};

/** \brief fitFrom(c, t, pose, score) over a batch of ChainFit jobs, on the CPU: the jobs side by
 * side (one job, or inside a parallel region: in the caller's thread, so that a fit may use a
 * parallel loop of its own). */
template <class Pose, class FitFrom>
std::vector<Pose> fitEach(const std::vector<ChainFit<Pose>>& jobs, FitFrom& fitFrom) {
  std::vector<Pose> out(jobs.size());
  const long n = static_cast<long>(jobs.size());
  detail::eachIndex(n, 1, [&](long j) {
    out[j] = fitFrom(jobs[j].chain, jobs[j].frame, jobs[j].start, jobs[j].score);
  });
  return out;
}

/** \brief A start that fitChainsBatched asks to be scored: `pose` in frame `frame` of chain
 * `chain`. */
template <class Pose>
struct ChainScore {
  int chain = 0, frame = 0;
  Pose pose;
};

/** \brief score(c, t, pose) over a batch of ChainScore items, on the CPU, side by side (in the
 * caller's thread inside a parallel region). */
template <class Pose, class Score>
std::vector<double> scoreEach(const std::vector<ChainScore<Pose>>& items, Score& score) {
  std::vector<double> out(items.size());
  const long n = static_cast<long>(items.size());
  detail::eachIndex(n, 4,
                    [&](long j) { out[j] = score(items[j].chain, items[j].frame, items[j].pose); });
  return out;
}

/** \brief A count of fitChainsBatched's batches of one kind, for timings: the calls, their
 * items and the seconds inside them. */
struct BatchTally {
  int calls = 0;
  std::size_t items = 0;
  double seconds = 0.0;
};

/** \brief `batch` (a score or fit batch) counted in `tally` at every call. */
template <class Batch>
auto tallied(BatchTally& tally, Batch batch) {
  return [&tally, batch](const auto& input) {
    const auto t0 = std::chrono::steady_clock::now();
    auto r = batch(input);
    tally.seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    ++tally.calls;
    tally.items += input.size();
    return r;
  };
}

/** \brief A score batch and the fits it decides, for a device that makes both in one call
 * (fitChainsBatched's `scoreFit`): item j's starts to score are starts[first .. first + count),
 * `place` holding each one's place among its frame's starts (rising within an item), and its
 * base is a start scored before, at place base_place with score base_score (none where
 * base_place < 0). */
template <class Pose>
struct ChainScoreFit {
  struct Item {
    int chain = 0, frame = 0;
    std::size_t first = 0, count = 0;
    double base_score = 0.0;
    int base_place = -1;
  };
  std::vector<ChainScore<Pose>> starts;
  std::vector<int> place;
  std::vector<Item> items;
};

/** \brief The answer to a ChainScoreFit: a score per start (the score batch's), and per item the
 * fit (the fit batch's, fitFrom(chain, frame, start, score)) from its winner where that is one of
 * its starts: `fitted[j]` the winner's index among item j's starts, -1 where the base or an
 * unscored place won (nothing fitted); `fits[j]` the pose. The winner: the first of the lowest
 * score by place (a score must be below the largest double to win; place 0 wins where none
 * does), scoreFitWinner's (score_fit.h). */
template <class Pose>
struct ChainScoreFitResult {
  std::vector<double> scores;
  std::vector<int> fitted;
  std::vector<Pose> fits;
};

// The steps of fitAlongChains with the fits and the scores in batches (defined below).
template <class Pose, class Starts, class ScoreBatch, class FitBatch, class Same>
std::vector<std::vector<Pose>> fitChainsBatched(
    int chains, int T, int ref, const Pose& identity, Starts starts, ScoreBatch scoreBatch,
    FitBatch fitBatch, Same same, bool speculate, int extra_rounds, int max_steps = kMaxChainSteps,
    int required = -1, std::vector<char>* complete = nullptr,
    const std::function<ChainScoreFitResult<Pose>(const ChainScoreFit<Pose>&)>* scoreFit = nullptr);

// The parallel steps of fitAlongChain, for several chains at once (defined below).
template <class Pose, class Starts, class Score, class FitFrom, class Same>
std::vector<std::vector<Pose>> fitAlongChains(int chains, int T, int ref, const Pose& identity,
                                              Starts starts, Score score, FitFrom fitFrom,
                                              Same same, int extra_rounds = -1,
                                              int max_steps = kMaxChainSteps);

/** \brief Fits every frame 0..T-1 but `ref` (which gets `identity`), in order away from `ref`
 * (chainFrames(T, ref, max_steps): ref+1, ref+2, ..., then ref-1, ref-2, ..., through key frames
 * on a side longer than max_steps), each from the first of its starts with the lowest score.
 *
 * - `starts(t, step, fits)` returns frame t's starts in their order (a std::vector of
 *   ChainStart<Pose>; at least one). With `fits` null it must return only the unchained ones (the
 *   same poses in the same relative order); otherwise the chained ones may use
 *   `(*fits)[step.before]` and `(*fits)[step.two_before]` (final when called; `step` is frame
 *   t's ChainStep in chainFrames(T, ref, max_steps)), and no other fit.
 * - `score(t, pose)` scores a start (lower is better).
 * - `fitFrom(t, pose, score)` returns the fit from the winning start and its score.
 * - `same(p, q)`: whether two poses are equal (bit for bit).
 *
 * With `parallel` (and score and fitFrom pure functions of their arguments) the result is the
 * same, computed with the frames side by side. A chain is otherwise serial: in the motion method
 * a merged part's 48 frames were one thread's work while the other cores waited.
 * 1. Every frame is fitted from the best of its unchained starts (in parallel).
 * 2. Every frame's chained starts are built from those fits of the frames before it, scored, and
 *    where one wins, the frame is fitted from it (in parallel).
 * 2b. On 4 threads or more, up to 6 more rounds fit again, in parallel, the frames whose inputs
 *    (the fits of the frames before) changed in the round before.
 * 3. Frame by frame along the chain, the result of the last round stands where the fits of the
 *    two frames before it are the ones it assumed (most frames); otherwise the frame's chained
 *    starts are scored, and it is fitted, again.
 * Written by us: the speculation is specific to this fit. */
template <class Pose, class Starts, class Score, class FitFrom, class Same>
std::vector<Pose> fitAlongChain(int T, int ref, const Pose& identity, Starts starts, Score score,
                                FitFrom fitFrom, Same same, bool parallel,
                                int max_steps = kMaxChainSteps) {
  if (!parallel) {
    std::vector<Pose> fit(T > 0 ? T : 0, identity);
    const ChainFrames frames = chainFrames(T, ref, max_steps);
    for (int t : frames.order) {
      const auto s = starts(t, frames.step[t], &fit);
      std::size_t best = 0;
      double r0 = std::numeric_limits<double>::max();
      for (std::size_t k = 0; k < s.size(); ++k) {
        const double r = score(t, s[k].pose);
        if (r < r0) r0 = r, best = k;
      }
      fit[t] = fitFrom(t, s[best].pose, r0);
    }
    return fit;
  }
  return fitAlongChains(
             1, T, ref, identity,
             [&](int, int t, const ChainStep& step, const std::vector<Pose>* fits) {
               return starts(t, step, fits);
             },
             [&](int, int t, const Pose& pose) { return score(t, pose); },
             [&](int, int t, const Pose& pose, double r0) { return fitFrom(t, pose, r0); }, same,
             -1, max_steps)
      .front();
}

/** \brief fitAlongChain's parallel steps for `chains` independent chains at once, each of T
 * frames with the same reference: `starts(c, t, step, fits)`, `score(c, t, pose)` and
 * `fitFrom(c, t, pose, r0)` as in fitAlongChain with the chain c first. Steps 1 and 2 of all the
 * chains' frames are one parallel loop each, and step 3 runs the chains side by side, so that a
 * few short chains keep many cores busy (the parts of a labelling fitted one after the other,
 * each over its frames, waited three times per part for the slowest of its frames). Returns
 * every chain's fits: the same as fitAlongChain (and the serial chain) gives for each.
 * `extra_rounds` (default: 6 on 4 threads or more, else 0) more parallel rounds before step 3
 * (see below) move serial fits of step 3 into parallel loops. */
template <class Pose, class Starts, class Score, class FitFrom, class Same>
std::vector<std::vector<Pose>> fitAlongChains(int chains, int T, int ref, const Pose& identity,
                                              Starts starts, Score score, FitFrom fitFrom,
                                              Same same, int extra_rounds, int max_steps) {
  return fitChainsBatched(
      chains, T, ref, identity, starts,
      [&](const std::vector<ChainScore<Pose>>& items) { return scoreEach(items, score); },
      [&](const std::vector<ChainFit<Pose>>& jobs) { return fitEach(jobs, fitFrom); }, same, true,
      extra_rounds, max_steps);
}

/** \brief fitAlongChains (`speculate`: its steps 1, 2, 2b and 3) or the chains frame after frame
 * (not `speculate`: step 3 alone, each frame from the best of all its starts, as the serial
 * fitAlongChain), with every fit and every score asked for in batches: `fitBatch(jobs)` returns,
 * for each ChainFit, fitFrom(chain, frame, start, score), and `scoreBatch(items)`, for each
 * ChainScore, score(chain, frame, pose), both in their input's order. Step 3 walks the chains
 * side by side, the frames as many steps from the reference at a time (both sides', and between
 * key frames every stretch's), so that those of all the chains are one batch. For a device that
 * fits and scores many frames at once (the CUDA module); on the CPU fitEach and scoreEach are the
 * batches. The same fits as fitAlongChains and the serial chains.
 *
 * Optional chains: with `required` (0 < required < chains; default, all), the chains from
 * `required` on ride along in the batches of the first `required` and never add a batch of their
 * own: the rounds of step 2b end when the required chains' end, and optional chains that would
 * make a score or fit batch without a required chain's item in it are given up. `complete`,
 * where given, gets one flag per chain: whether its fits are final (always, for a required
 * chain); a given-up chain's fits are not. The required chains get the fits and the batches they
 * would get alone, and a complete chain's fits are the ones it would get alone (the rounds only
 * guess: step 3 checks every guess). Written for speculative fits, which must not make the fits
 * that are needed now wait.
 *
 * With `scoreFit` (non-null), each score batch and the fit batch it decides are one call
 * (ChainScoreFit): a device then makes one round trip where it made two. The same scores, the
 * same winners and the same fits, so the same results; an optional chain is then given up only
 * where a score batch would hold it alone (its fits ride in the call of its scores). */
template <class Pose, class Starts, class ScoreBatch, class FitBatch, class Same>
std::vector<std::vector<Pose>> fitChainsBatched(
    int chains, int T, int ref, const Pose& identity, Starts starts, ScoreBatch scoreBatch,
    FitBatch fitBatch, Same same, bool speculate, int extra_rounds, int max_steps, int required,
    std::vector<char>* complete,
    const std::function<ChainScoreFitResult<Pose>(const ChainScoreFit<Pose>&)>* scoreFit) {
  const int C = chains > 0 ? chains : 0, F = T > 0 ? T : 0;
  const int R = required > 0 && required < C ? required : C;  // the required chains, first
  std::vector<char> alive(static_cast<std::size_t>(C), 1);
  const ChainFrames chain = chainFrames(F, ref, max_steps);
  // Default: 6 more rounds on 4 threads or more (each costs fits that step 3 might not need;
  // on 2 threads step 3's chains side by side keep both busy).
  if (extra_rounds < 0) extra_rounds = omp_get_max_threads() >= 4 ? 6 : 0;
  if (!speculate) extra_rounds = 0;
  const std::vector<Pose> frames_of(static_cast<std::size_t>(F), identity);
  std::vector<std::vector<Pose>> fit(C, frames_of);
  constexpr double kNone = std::numeric_limits<double>::max();
  using Job = ChainFit<Pose>;
  // Frame t's winner among its starts (the first of the lowest score), with the unchained ones
  // scored already: the best of them is index `spec_k` among the unchained, scored `spec_r`.
  // An unchained start that lost to it cannot win: it scores above it, or the same and later.
  // Without speculation nothing is scored ahead: every start is scored here.
  constexpr double kLost = std::numeric_limits<double>::infinity();
  // Per (chain, frame), at c * F + t.
  std::vector<double> spec_r(static_cast<std::size_t>(C) * F, kNone);
  std::vector<std::size_t> spec_k(static_cast<std::size_t>(C) * F, 0);
  auto at_ct = [F](int c, int t) { return static_cast<std::size_t>(c) * F + t; };
  // Optional chains that alone would make a batch (no required chain's item in `batch`) are
  // given up; returns whether any was.
  auto giveUpAlone = [&](const auto& batch) {
    if (R == C || batch.empty()) return false;
    for (const auto& x : batch)
      if (x.chain < R) return false;
    for (const auto& x : batch) alive[x.chain] = 0;
    return true;
  };
  // Which of a frame's starts it scores here (the others are spec's).
  auto scoredHere = [&](const ChainStart<Pose>& x) { return x.chained || !speculate; };
  // `scored`: the scores of the starts scoredHere, in their order.
  auto winner = [&](int c, int t, const std::vector<ChainStart<Pose>>& s, const double* scored,
                    double& r0) {
    std::size_t best = 0, unchained = 0;
    r0 = kNone;
    for (std::size_t k = 0; k < s.size(); ++k) {
      double r;
      if (scoredHere(s[k]))
        r = *scored++;
      else
        r = unchained++ == spec_k[at_ct(c, t)] ? spec_r[at_ct(c, t)] : kLost;
      if (r < r0) r0 = r, best = k;
    }
    return best;
  };
  // The starts of every (chain, frame) of `todo` (side by side) and the scores of those listed
  // by `keep` (one batch): at[j] is where todo[j]'s scores begin in `scores`. With `fused` (and
  // scoreFit), the batch is a ChainScoreFit whose items' bases are base(j, s[j]) (a place and
  // a score, or a place < 0), and the fits it decides come back in *fused.
  using Starts_ = std::vector<ChainStart<Pose>>;
  using Fused = ChainScoreFitResult<Pose>;
  auto startsAndScores = [&](const std::vector<std::pair<int, int>>& todo,
                             const std::vector<std::vector<Pose>>* from, auto keep,
                             std::vector<Starts_>& s, std::vector<std::size_t>& at,
                             std::vector<double>& scores, Fused* fused = nullptr,
                             const std::function<std::pair<int, double>(
                                 std::size_t, const Starts_&)>& base = nullptr) {
    const long n = static_cast<long>(todo.size());
    s.assign(todo.size(), Starts_());
    detail::eachIndex(n, 4, [&](long j) {
      const auto [c, t] = todo[j];
      s[j] = starts(c, t, chain.step[t], from ? &(*from)[c] : nullptr);
    });
    ChainScoreFit<Pose> batch;
    std::vector<ChainScore<Pose>>& items = batch.starts;
    std::size_t listed = 0;
    for (const Starts_& x : s) listed += x.size();
    items.reserve(listed);
    auto list = [&] {
      items.clear();
      batch.place.clear();
      batch.items.clear();
      at.assign(todo.size() + 1, 0);
      for (std::size_t j = 0; j < todo.size(); ++j) {
        at[j] = items.size();
        if (!alive[todo[j].first]) continue;
        for (std::size_t k = 0; k < s[j].size(); ++k)
          if (keep(s[j][k])) {
            items.push_back({todo[j].first, todo[j].second, s[j][k].pose});
            batch.place.push_back(static_cast<int>(k));
          }
        if (fused) {
          typename ChainScoreFit<Pose>::Item it;
          it.chain = todo[j].first;
          it.frame = todo[j].second;
          it.first = at[j];
          it.count = items.size() - at[j];
          if (base) std::tie(it.base_place, it.base_score) = base(j, s[j]);
          batch.items.push_back(it);
        }
      }
      at[todo.size()] = items.size();
    };
    list();
    if (giveUpAlone(items)) list();
    scores.clear();
    const bool fuse = fused && scoreFit;
    if (fuse) *fused = Fused();
    if (!items.empty()) {
      if (fuse) {
        *fused = (*scoreFit)(batch);
        scores = fused->scores;
        if (fused->fitted.size() != batch.items.size() || fused->fits.size() != batch.items.size())
          throw Error("chained fit: a score-and-fit batch returned " +
                      std::to_string(fused->fits.size()) + " fits for " +
                      std::to_string(batch.items.size()) + " frames");
      } else {
        scores = scoreBatch(items);
      }
    }
    if (scores.size() != items.size())
      throw Error("chained fit: a score batch returned " + std::to_string(scores.size()) +
                  " scores for " + std::to_string(items.size()));
  };
  // Item i of a fused batch (the i-th listed of `todo`, which lists only alive chains' frames)
  // by todo index: listed[j], -1 for a frame of a given-up chain.
  auto listedOf = [&](const std::vector<std::pair<int, int>>& todo) {
    std::vector<int> listed(todo.size(), -1);
    int i = 0;
    for (std::size_t j = 0; j < todo.size(); ++j)
      if (alive[todo[j].first]) listed[j] = i++;
    return listed;
  };
  // The fused batch's fit of item i, whose winner is its scored start `scored_index` by the
  // caller's scores: the device's winner must be the same start.
  auto fusedFit = [&](const Fused& f, int i, std::size_t scored_index) -> const Pose& {
    if (i < 0 || f.fitted[static_cast<std::size_t>(i)] != static_cast<int>(scored_index))
      throw Error("chained fit: a score-and-fit batch chose another start than its scores do");
    return f.fits[static_cast<std::size_t>(i)];
  };
  // The jobs of the slots marked in `marked`, fitted in one batch, each result to out[c][t].
  auto fitMarked = [&](const std::vector<Job>& job, const std::vector<char>& marked,
                       std::vector<std::vector<Pose>>& out) {
    std::vector<Job> jobs;
    std::size_t n = 0;
    for (char m : marked) n += m != 0;
    jobs.reserve(n);
    for (std::size_t j = 0; j < job.size(); ++j)
      if (marked[j] && alive[job[j].chain]) jobs.push_back(job[j]);
    if (giveUpAlone(jobs)) return;
    if (jobs.empty()) return;
    const std::vector<Pose> res = fitBatch(jobs);
    for (std::size_t j = 0; j < jobs.size(); ++j) out[jobs[j].chain][jobs[j].frame] = res[j];
  };
  // The jobs of `todo` (chain, frame) pairs given the fits `from` of the frames before them:
  // each frame's winning start is fitted, except an unchained winner under speculation (its fit
  // is spec's); the results go to out[c][t].
  std::vector<std::vector<Pose>> spec(C, frames_of);
  auto fitGivenAll = [&](const std::vector<std::pair<int, int>>& todo,
                         const std::vector<std::vector<Pose>>& from,
                         std::vector<std::vector<Pose>>& out) {
    std::vector<Starts_> s;
    std::vector<std::size_t> at;
    std::vector<double> scores;
    // With scoreFit: the frame's unscored winner so far (spec_k among its unchained starts,
    // scored spec_r in step 1) as its base.
    Fused f;
    const bool fuse = scoreFit != nullptr;
    auto base = [&](std::size_t j, const Starts_& sj) -> std::pair<int, double> {
      const auto [c, t] = todo[j];
      std::size_t u = 0;
      for (std::size_t k = 0; k < sj.size(); ++k)
        if (!scoredHere(sj[k]) && u++ == spec_k[at_ct(c, t)])
          return {static_cast<int>(k), spec_r[at_ct(c, t)]};
      return {-1, 0.0};
    };
    startsAndScores(todo, &from, scoredHere, s, at, scores, fuse ? &f : nullptr, base);
    const std::vector<int> listed = fuse ? listedOf(todo) : std::vector<int>();
    std::vector<Job> job(fuse ? 0 : todo.size());
    std::vector<char> fitted(fuse ? 0 : todo.size(), 0);
    for (std::size_t j = 0; j < todo.size(); ++j) {
      const auto [c, t] = todo[j];
      if (!alive[c]) continue;
      double r0;
      const std::size_t best = winner(c, t, s[j], scores.data() + at[j], r0);
      if (scoredHere(s[j][best])) {
        if (fuse) {
          std::size_t scored_index = 0;
          for (std::size_t k = 0; k < best; ++k) scored_index += scoredHere(s[j][k]) ? 1 : 0;
          out[c][t] = fusedFit(f, listed[j], scored_index);
        } else {
          job[j] = {c, t, s[j][best].pose, r0};
          fitted[j] = 1;
        }
      } else {
        out[c][t] = spec[c][t];
      }
    }
    if (!fuse) fitMarked(job, fitted, out);
  };
  // Whether the fits that frame t's chained starts may use are the same in a and b: the frame
  // before it and the frame two before (chainFrames).
  auto sameInputs = [&](int c, int t, const std::vector<std::vector<Pose>>& a,
                        const std::vector<std::vector<Pose>>& b) {
    const int t1 = chain.step[t].before, t2 = chain.step[t].two_before;
    return same(a[c][t1], b[c][t1]) && (t2 < 0 || same(a[c][t2], b[c][t2]));
  };
  std::vector<std::vector<Pose>> guess(C, frames_of), before;
  if (speculate) {
    // Step 1: every frame from the best of its unchained starts.
    std::vector<std::pair<int, int>> all;
    for (int c = 0; c < C; ++c)
      for (int t = 0; t < F; ++t)
        if (t != ref) all.push_back({c, t});
    {
      std::vector<Starts_> s;
      std::vector<std::size_t> at;
      std::vector<double> scores;
      Fused f;
      const bool fuse = scoreFit != nullptr;
      startsAndScores(
          all, nullptr, [](const ChainStart<Pose>&) { return true; }, s, at, scores,
          fuse ? &f : nullptr);
      const std::vector<int> listed = fuse ? listedOf(all) : std::vector<int>();
      std::vector<Job> job(all.size());
      std::vector<char> fitted(all.size(), 0);
      for (std::size_t j = 0; j < all.size(); ++j) {
        if (s[j].empty()) continue;
        const auto [c, t] = all[j];
        for (std::size_t k = 0; k < s[j].size(); ++k) {
          const double r = scores[at[j] + k];
          if (r < spec_r[at_ct(c, t)]) spec_r[at_ct(c, t)] = r, spec_k[at_ct(c, t)] = k;
        }
        if (fuse) {
          if (alive[c]) spec[c][t] = fusedFit(f, listed[j], spec_k[at_ct(c, t)]);
          continue;
        }
        job[j] = {c, t, s[j][spec_k[at_ct(c, t)]].pose, spec_r[at_ct(c, t)]};
        fitted[j] = 1;
      }
      if (!fuse) fitMarked(job, fitted, spec);
    }
    // Step 2: frame t assumes that the frames before it kept their unchained fits (spec).
    fitGivenAll(all, spec, guess);
    // More rounds on many threads (a Jacobi iteration of the chain): round r fits again, from
    // round r-1's fits of the frames before, every frame whose inputs changed in round r-1; the
    // others keep their fit (the same inputs give the same fit). A run of n frames where the
    // chained start wins is final after n rounds, which step 3 would fit one after the other.
    // `before` holds the fits each frame of `guess` was computed from.
    // changed[c * F + t]: whether frame t's fit in `guess` differs from the one in `before`
    // (only a frame fitted again in the round can differ), so that a frame's inputs are compared
    // once a round, not by each frame that reads them.
    before = spec;
    std::vector<char> changed(static_cast<std::size_t>(C) * F, 0);
    for (int c = 0; c < C; ++c)
      for (int t = 0; t < F; ++t) changed[at_ct(c, t)] = !same(guess[c][t], before[c][t]);
    std::vector<std::vector<Pose>> next;
    std::vector<std::pair<int, int>> redo;
    for (int round = 2; round <= extra_rounds + 1; ++round) {
      redo.clear();
      std::size_t required_redo = 0;
      for (int c = 0; c < C; ++c) {
        for (int t = 0; t < F && alive[c]; ++t) {
          if (t == ref) continue;
          const int t1 = chain.step[t].before, t2 = chain.step[t].two_before;
          if (changed[at_ct(c, t1)] || (t2 >= 0 && changed[at_ct(c, t2)])) redo.push_back({c, t});
        }
        if (c + 1 == R) required_redo = redo.size();
      }
      if (required_redo == 0) break;  // the optional chains' rounds alone: left to step 3
      next = guess;  // the same shape every round: its storage is reused
      fitGivenAll(redo, guess, next);
      std::fill(changed.begin(), changed.end(), 0);
      for (const auto& [c, t] : redo) changed[at_ct(c, t)] = !same(next[c][t], guess[c][t]);
      before.swap(guess);
      guess.swap(next);
    }
  }
  // Step 3, the frames as many steps from the reference (chainFrames: the frames both sides of
  // it, and between key frames those of every stretch) of every chain at a time: the last
  // round's fit stands where the frames before it are as it assumed (most frames); otherwise the
  // frame's starts are scored, and it is fitted, again. spec[c][ref] is the identity, as
  // fit[c][ref] is.
  std::vector<int> depth(static_cast<std::size_t>(F), 0);
  std::vector<std::vector<int>> at_depth;
  for (int t : chain.order) {
    depth[t] = depth[chain.step[t].before] + 1;
    if (static_cast<int>(at_depth.size()) < depth[t]) at_depth.resize(depth[t]);
    at_depth[depth[t] - 1].push_back(t);
  }
  std::vector<std::pair<int, int>> redo;
  for (const std::vector<int>& frames : at_depth) {
    redo.clear();
    for (int t : frames)
      for (int c = 0; c < C; ++c) {
        if (!alive[c]) continue;
        if (speculate && sameInputs(c, t, fit, before))
          fit[c][t] = guess[c][t];
        else
          redo.push_back({c, t});
      }
    fitGivenAll(redo, fit, fit);  // an optional chain alone in it is given up there
  }
  if (complete) complete->assign(alive.begin(), alive.end());
  return fit;
}

/** \brief The fits of `chains` chains (callables as in fitAlongChains), whichever way keeps the
 * threads busy: with at least 4 times as many chains as threads (or one thread, or inside a
 * parallel region) each chain frame after frame, the chains side by side; otherwise
 * fitAlongChains, whose speculation costs fits that a serial chain does not make. The same fits
 * either way. */
template <class Pose, class Starts, class Score, class FitFrom, class Same>
std::vector<std::vector<Pose>> fitChains(int chains, int T, int ref, const Pose& identity,
                                         Starts starts, Score score, FitFrom fitFrom, Same same,
                                         int max_steps = kMaxChainSteps) {
  const int C = chains > 0 ? chains : 0;
  const int threads = omp_in_parallel() ? 1 : omp_get_max_threads();
  if (threads > 1 && C < 4 * threads)
    return fitAlongChains(C, T, ref, identity, starts, score, fitFrom, same, -1, max_steps);
  std::vector<std::vector<Pose>> out(C);
  detail::eachIndex(C, 1, [&](long c) {
    out[c] = fitAlongChain(
        T, ref, identity,
        [&](int t, const ChainStep& step, const std::vector<Pose>* fit) {
          return starts(static_cast<int>(c), t, step, fit);
        },
        [&](int t, const Pose& P) { return score(static_cast<int>(c), t, P); },
        [&](int t, const Pose& P, double r0) { return fitFrom(static_cast<int>(c), t, P, r0); },
        same, false, max_steps);
  });
  return out;
}

}  // namespace segmentation
}  // namespace pcl_animseg
