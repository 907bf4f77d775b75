// fitAlongChain: frames fitted in parallel must give what the serial chain gives, whichever start
// wins (chained or not, ties included), for a reference frame first, last or in the middle.
#include <gtest/gtest.h>
#include <omp.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/segmentation/chained_fit.h>

#include <algorithm>
#include <cmath>
#include <functional>
#include <random>
#include <vector>

namespace seg = pcl_animseg::segmentation;

namespace {

/** A toy tracking problem on the real line: the pose of frame t is a number, target[t] the true
 * one. Two unchained guesses per frame (good in most frames, both lost in some) and two chained
 * starts (the previous fit and a constant-velocity guess), in the motion method's order. Scores
 * are rounded so that ties happen; the fit moves halfway to the target and keeps the better of
 * start and result, as the ICP fits do. */
struct Toy {
  std::vector<double> target, a, b;
  int chained_wins = 0;  // counted by the serial run

  Toy(int T, unsigned seed) {
    std::mt19937 rng(seed);
    std::normal_distribution<double> step(0.0, 1.0), noise(0.0, 0.3);
    std::uniform_real_distribution<double> u(0.0, 1.0);
    double x = 0.0;
    for (int t = 0; t < T; ++t) {
      x += step(rng);
      target.push_back(x);
      const bool lost = u(rng) < 0.35;
      a.push_back(x + (lost ? 5.0 + 5.0 * u(rng) : noise(rng)));
      b.push_back(u(rng) < 0.5 ? a.back() : x + (lost ? -6.0 : noise(rng)));
    }
  }
  double score(int t, double p) const { return std::round(4.0 * std::fabs(p - target[t])) / 4.0; }
  double fitFrom(int t, double p, double r0) const {
    const double q = p + 0.5 * (target[t] - p);
    return score(t, q) <= r0 ? q : p;
  }
  // Frame t's starts, in the motion method's order.
  std::vector<seg::ChainStart<double>> starts(int t, const seg::ChainStep& st,
                                              const std::vector<double>* fit) const {
    std::vector<seg::ChainStart<double>> s{{a[t], false}};
    if (fit) s.push_back({(*fit)[st.before], true});
    s.push_back({b[t], false});
    if (fit && st.two_before >= 0)
      s.push_back({2.0 * (*fit)[st.before] - (*fit)[st.two_before], true});
    return s;
  }
  std::vector<double> run(int ref, bool parallel, int* wins = nullptr) const {
    const int T = static_cast<int>(target.size());
    auto starts = [&](int t, const seg::ChainStep& st, const std::vector<double>* fit) {
      const std::vector<seg::ChainStart<double>> s = this->starts(t, st, fit);
      if (wins && fit) {  // serial run: which start wins (the first of the lowest score)
        std::size_t best = 0;
        for (std::size_t k = 1; k < s.size(); ++k)
          if (score(t, s[k].pose) < score(t, s[best].pose)) best = k;
        *wins += s[best].chained;
      }
      return s;
    };
    auto sc = [&](int t, double p) { return score(t, p); };
    auto fit = [&](int t, double p, double r0) { return fitFrom(t, p, r0); };
    auto same = [](double p, double q) { return p == q; };
    return seg::fitAlongChain(T, ref, 0.0, starts, sc, fit, same, parallel);
  }
};

}  // namespace

TEST(ChainedFit, ParallelEqualsSerialWhicheverStartWins) {
  const int before = omp_get_max_threads();
  omp_set_num_threads(4);
  int total_wins = 0;
  // 48 frames: single steps; 130: key frames (3 apart from the first or the last frame, 2 from
  // the middle).
  for (const int T : {48, 130})
    for (unsigned seed = 1; seed <= 20; ++seed) {
      const Toy toy(T, seed);
      for (int ref : {0, T / 2 - 1, T - 1}) {
        int wins = 0;
        const std::vector<double> serial = toy.run(ref, false, &wins);
        total_wins += wins;
        const std::vector<double> parallel = toy.run(ref, true);
        ASSERT_EQ(serial.size(), static_cast<std::size_t>(T));
        EXPECT_EQ(serial[ref], 0.0) << "the reference frame keeps the identity";
        for (int t = 0; t < T; ++t)
          EXPECT_EQ(serial[t], parallel[t])
              << "T " << T << " seed " << seed << " ref " << ref << " frame " << t;
      }
    }
  omp_set_num_threads(before);
  // The chained starts won in many frames (the lost ones): the check pass was exercised.
  EXPECT_GT(total_wins, 100);
}

// chainFrames: single steps up to 48 frames on a side; longer sides through key frames at most 4
// apart, each frame after one nearer the reference, no frame much more than 48 steps from it.
TEST(ChainedFit, KeyFramesOnLongSides) {
  auto depthOf = [](const seg::ChainFrames& c, int ref) {
    std::vector<int> depth(c.step.size(), 0);
    int deepest = 0;
    for (int t : c.order) {
      EXPECT_GE(c.step[t].before, 0) << t;
      EXPECT_EQ(depth[t], 0) << t << " listed twice";
      depth[t] = depth[c.step[t].before] + 1;  // its frame before was listed before it
      EXPECT_NE(t, ref);
      EXPECT_LT(std::abs(c.step[t].before - ref), std::abs(t - ref)) << t;
      deepest = std::max(deepest, depth[t]);
    }
    return deepest;
  };
  const seg::ChainFrames short_side = seg::chainFrames(49, 0);
  ASSERT_EQ(short_side.order.size(), 48u);
  for (int t = 1; t < 49; ++t) {
    EXPECT_EQ(short_side.step[t].before, t - 1);
    EXPECT_EQ(short_side.step[t].two_before, t >= 2 ? t - 2 : -1);
  }
  EXPECT_EQ(depthOf(short_side, 0), 48);
  const seg::ChainFrames middle = seg::chainFrames(60, 30);  // 30 and 29 frames a side
  EXPECT_EQ(middle.step[31].before, 30);
  EXPECT_EQ(middle.step[29].before, 30);
  EXPECT_EQ(middle.step[27].two_before, 29);
  const seg::ChainFrames long_side = seg::chainFrames(160, 0);  // key frames 4 apart
  ASSERT_EQ(long_side.order.size(), 159u);
  EXPECT_EQ(long_side.step[4].before, 0);
  EXPECT_EQ(long_side.step[4].two_before, -1);
  EXPECT_EQ(long_side.step[8].before, 4);
  EXPECT_EQ(long_side.step[8].two_before, 0);
  EXPECT_EQ(long_side.step[9].before, 8);
  EXPECT_EQ(long_side.step[9].two_before, -1);
  EXPECT_EQ(long_side.step[11].two_before, 9);
  EXPECT_LE(depthOf(long_side, 0), 48 + 3);
  const seg::ChainFrames very_long = seg::chainFrames(1000, 500);  // at most 4 apart
  EXPECT_EQ(very_long.step[504].before, 500);
  EXPECT_EQ(very_long.step[496].before, 500);
  EXPECT_LE(depthOf(very_long, 500), 125 + 3);
  EXPECT_TRUE(seg::chainFrames(1, 0).order.empty());
  EXPECT_TRUE(seg::chainFrames(0, 0).order.empty());
  // Shorter chains asked for (the rigid motions' 12 steps): 48 frames through key frames 4
  // apart, 14 steps deep; 20 frames 2 apart; 13 frames single steps.
  const seg::ChainFrames rigid48 = seg::chainFrames(48, 0, 12);
  EXPECT_EQ(rigid48.step[4].before, 0);
  EXPECT_EQ(rigid48.step[5].before, 4);
  EXPECT_EQ(depthOf(rigid48, 0), 14);
  EXPECT_EQ(seg::chainFrames(20, 0, 12).step[2].before, 0);
  EXPECT_EQ(depthOf(seg::chainFrames(13, 0, 12), 0), 12);
  EXPECT_EQ(depthOf(seg::chainFrames(13, 0, 0), 0), 5);  // at least one step: 4 apart
}

TEST(ChainedFit, ChainedStartsRecoverLostFrames) {
  // Without the chain (unchained starts only) a lost frame stays lost; with it, it is found.
  const Toy toy(48, 7);
  const std::vector<double> fit = toy.run(0, true);
  int lost_unchained = 0, lost_chained = 0;
  for (int t = 1; t < 48; ++t) {
    const double best_guess = std::min(toy.score(t, toy.a[t]), toy.score(t, toy.b[t]));
    lost_unchained += best_guess > 3.0;
    lost_chained += toy.score(t, fit[t]) > 3.0;
  }
  EXPECT_GT(lost_unchained, 5);
  EXPECT_LT(lost_chained, lost_unchained);
}

// Optional chains (the motion method's speculative merge fits) ride along in the required
// chains' batches: the required chains get the fits and the batches they get alone, a complete
// optional chain its own serial fits, and one that would need a batch of its own is given up.
TEST(ChainedFit, OptionalChainsAddNoBatchAndTheCompleteOnesAreTheirOwnFits) {
  const int T = 48, ref = 0, chains = 10;
  std::vector<Toy> toys;
  for (int c = 0; c < chains; ++c) toys.emplace_back(T, 300 + c);
  auto starts = [&](int c, int t, const seg::ChainStep& st, const std::vector<double>* fit) {
    return toys[c].starts(t, st, fit);
  };
  auto same = [](double p, double q) { return p == q; };
  struct Counts {
    int score_batches = 0, fit_batches = 0;
  };
  auto batchesOf = [&](Counts& n, const std::vector<int>& which) {
    // chain c of the call is toy which[c]
    auto scoreBatch = [&n, &toys, which](const std::vector<seg::ChainScore<double>>& items) {
      ++n.score_batches;
      std::vector<double> out;
      for (const auto& x : items) out.push_back(toys[which[x.chain]].score(x.frame, x.pose));
      return out;
    };
    auto fitBatch = [&n, &toys, which](const std::vector<seg::ChainFit<double>>& jobs) {
      ++n.fit_batches;
      std::vector<double> out;
      for (const auto& j : jobs)
        out.push_back(toys[which[j.chain]].fitFrom(j.frame, j.start, j.score));
      return out;
    };
    return std::make_pair(scoreBatch, fitBatch);
  };
  int complete_seen = 0, given_up = 0;
  for (int main = 0; main < chains; ++main) {
    // Alone, then with the other nine toys as optional chains.
    Counts alone_n;
    const std::vector<int> one{main};
    auto [s1, f1] = batchesOf(alone_n, one);
    auto starts1 = [&](int, int t, const seg::ChainStep& st, const std::vector<double>* fit) {
      return starts(main, t, st, fit);
    };
    const std::vector<std::vector<double>> alone =
        seg::fitChainsBatched(1, T, ref, 0.0, starts1, s1, f1, same, true, 6);
    std::vector<int> which{main};
    for (int c = 0; c < chains; ++c)
      if (c != main) which.push_back(c);
    Counts with_n;
    auto [s2, f2] = batchesOf(with_n, which);
    auto startsW = [&](int c, int t, const seg::ChainStep& st, const std::vector<double>* fit) {
      return starts(which[c], t, st, fit);
    };
    std::vector<char> complete;
    const std::vector<std::vector<double>> with = seg::fitChainsBatched(
        chains, T, ref, 0.0, startsW, s2, f2, same, true, 6, seg::kMaxChainSteps, 1, &complete);
    ASSERT_EQ(with.size(), static_cast<std::size_t>(chains));
    ASSERT_EQ(complete.size(), static_cast<std::size_t>(chains));
    EXPECT_TRUE(complete[0]);
    EXPECT_EQ(with[0], alone[0]) << main;
    EXPECT_EQ(with[0], toys[main].run(ref, false)) << main;
    EXPECT_EQ(with_n.score_batches, alone_n.score_batches) << main;
    EXPECT_EQ(with_n.fit_batches, alone_n.fit_batches) << main;
    for (int c = 1; c < chains; ++c) {
      if (complete[c]) {
        ++complete_seen;
        EXPECT_EQ(with[c], toys[which[c]].run(ref, false)) << main << " optional " << which[c];
      } else {
        ++given_up;
      }
    }
  }
  // Both cases happen with these toys (a chain whose fits settle in fewer rounds than another's).
  EXPECT_GT(complete_seen, 0);
  EXPECT_GT(given_up, 0);
}

// scoreFitWinner: the first of the lowest score by place, the base among the starts; a score
// must be below the largest double to win, and place 0 wins where none is (fitChainsBatched's
// winner, whose unchained losers score +infinity).
TEST(ChainedFit, AScoreAndFitsWinnerIsTheFirstOfTheLowestScoreByPlace) {
  const double kMax = std::numeric_limits<double>::max();
  double r0 = 0.0;
  const double s1[] = {2.0, 1.0, 1.0};
  const int p1[] = {0, 2, 3};
  EXPECT_EQ(seg::scoreFitWinner(s1, p1, 3, 0.0, -1, r0), 1);  // ties: the lower place
  EXPECT_EQ(r0, 1.0);
  EXPECT_EQ(seg::scoreFitWinner(s1, p1, 3, 1.0, 1, r0), -1);  // the base, place 1, ties first
  EXPECT_EQ(r0, 1.0);
  EXPECT_EQ(seg::scoreFitWinner(s1, p1, 3, 1.0, 4, r0), 1);  // a base after it ties too late
  EXPECT_EQ(seg::scoreFitWinner(s1, p1, 3, 0.5, 4, r0), -1);
  EXPECT_EQ(r0, 0.5);
  const double s2[] = {kMax, std::numeric_limits<double>::infinity()};
  const int p2[] = {0, 1};
  EXPECT_EQ(seg::scoreFitWinner(s2, p2, 2, kMax, 2, r0), 0);  // none below: place 0
  EXPECT_EQ(r0, kMax);
  const int p3[] = {1, 2};
  EXPECT_EQ(seg::scoreFitWinner(s2, p3, 2, kMax, 0, r0), -1);  // place 0 is the base
  EXPECT_EQ(seg::scoreFitWinner(s2, p3, 2, 0.0, -1, r0), -1);  // place 0 is not scored
  EXPECT_EQ(seg::scoreFitWinner(nullptr, nullptr, 0, 3.0, 0, r0), -1);
  EXPECT_EQ(r0, 3.0);
}

// Each score batch and the fits it decides in one call (fitChainsBatched's scoreFit) give the
// fits of the two batches, with one call per score batch and no fit batch, with and without the
// speculation; with optional chains the required chain's fits and calls are its own.
TEST(ChainedFit, ScoreAndFitInOneCallGivesTheFitsOfTwoBatches) {
  const int T = 48, chains = 10;
  std::vector<Toy> toys;
  for (int c = 0; c < chains; ++c) toys.emplace_back(T, 500 + c);
  auto starts = [&](int c, int t, const seg::ChainStep& st, const std::vector<double>* fit) {
    return toys[c].starts(t, st, fit);
  };
  auto same = [](double p, double q) { return p == q; };
  int scores_n = 0, fits_n = 0, fused_n = 0, fused_fits = 0, unfitted = 0;
  auto scoreBatch = [&](const std::vector<seg::ChainScore<double>>& items) {
    ++scores_n;
    std::vector<double> out;
    for (const auto& x : items) out.push_back(toys[x.chain].score(x.frame, x.pose));
    return out;
  };
  auto fitBatch = [&](const std::vector<seg::ChainFit<double>>& jobs) {
    ++fits_n;
    std::vector<double> out;
    for (const auto& j : jobs) out.push_back(toys[j.chain].fitFrom(j.frame, j.start, j.score));
    return out;
  };
  const std::function<seg::ChainScoreFitResult<double>(const seg::ChainScoreFit<double>&)> fused =
      [&](const seg::ChainScoreFit<double>& b) {
        ++fused_n;
        seg::ChainScoreFitResult<double> r;
        for (const auto& x : b.starts) r.scores.push_back(toys[x.chain].score(x.frame, x.pose));
        for (const auto& it : b.items) {
          double r0;
          const int w = seg::scoreFitWinner(r.scores.data() + it.first, b.place.data() + it.first,
                                            it.count, it.base_score, it.base_place, r0);
          r.fitted.push_back(w);
          r.fits.push_back(
              w < 0 ? 0.0 : toys[it.chain].fitFrom(it.frame, b.starts[it.first + w].pose, r0));
          fused_fits += w >= 0;
          unfitted += w < 0;
        }
        return r;
      };
  for (const int ref : {0, 20, 47})
    for (const bool speculate : {true, false}) {
      scores_n = fits_n = fused_n = 0;
      const auto two = seg::fitChainsBatched(chains, T, ref, 0.0, starts, scoreBatch, fitBatch,
                                             same, speculate, 6);
      const int two_scores = scores_n;
      EXPECT_GT(fits_n, 0);
      scores_n = fits_n = 0;
      const auto one =
          seg::fitChainsBatched(chains, T, ref, 0.0, starts, scoreBatch, fitBatch, same, speculate,
                                6, seg::kMaxChainSteps, -1, nullptr, &fused);
      EXPECT_EQ(one, two) << ref << " " << speculate;
      for (int c = 0; c < chains; ++c) EXPECT_EQ(one[c], toys[c].run(ref, false)) << c;
      EXPECT_EQ(scores_n, 0);
      EXPECT_EQ(fits_n, 0);
      EXPECT_EQ(fused_n, two_scores) << ref << " " << speculate;
    }
  EXPECT_GT(fused_fits, 0);
  EXPECT_GT(unfitted, 0);  // frames whose unchained fit stood (the speculation's)
  // Chain 0 required, the other nine optional: its fits and its calls as alone.
  auto toyStarts = [&](int c) {
    return [&, c](int, int t, const seg::ChainStep& st, const std::vector<double>* fit) {
      return toys[c].starts(t, st, fit);
    };
  };
  fused_n = 0;
  const auto alone = seg::fitChainsBatched(1, T, 0, 0.0, toyStarts(0), scoreBatch, fitBatch, same,
                                           true, 6, seg::kMaxChainSteps, -1, nullptr, &fused);
  const int alone_calls = fused_n;
  fused_n = 0;
  std::vector<char> complete;
  const auto with = seg::fitChainsBatched(chains, T, 0, 0.0, starts, scoreBatch, fitBatch, same,
                                          true, 6, seg::kMaxChainSteps, 1, &complete, &fused);
  EXPECT_EQ(with[0], alone[0]);
  EXPECT_EQ(fused_n, alone_calls);
  ASSERT_EQ(complete.size(), static_cast<std::size_t>(chains));
  EXPECT_TRUE(complete[0]);
  for (int c = 1; c < chains; ++c) {
    if (complete[c]) {
      EXPECT_EQ(with[c], toys[c].run(0, false)) << c;
    }
  }
}

TEST(ChainedFit, SingleFrameAndEmptySequence) {
  auto starts = [](int, const seg::ChainStep&, const std::vector<double>*) {
    return std::vector<seg::ChainStart<double>>{{1.0, false}};
  };
  auto score = [](int, double p) { return p; };
  auto fit = [](int, double p, double) { return p; };
  auto same = [](double p, double q) { return p == q; };
  for (bool parallel : {false, true}) {
    EXPECT_EQ(seg::fitAlongChain(1, 0, 0.0, starts, score, fit, same, parallel),
              std::vector<double>{0.0});
    EXPECT_TRUE(seg::fitAlongChain(0, 0, 0.0, starts, score, fit, same, parallel).empty());
  }
}

TEST(ChainedFit, SeveralChainsAtOnceEqualEachChainAlone) {
  // fitAlongChains over 12 toy chains (each its own seed) must give each chain's serial fits; 48
  // frames, and 110 (key frames 3 apart from frame 0, single steps from frame 60).
  const int chains = 12;
  const int before = omp_get_max_threads();
  for (const int T : {48, 110}) {
    std::vector<Toy> toys;
    for (int c = 0; c < chains; ++c) toys.emplace_back(T, 100 + c);
    omp_set_num_threads(4);
    for (int ref : {0, T == 48 ? 30 : 60}) {
      auto starts = [&](int c, int t, const seg::ChainStep& st, const std::vector<double>* fit) {
        return toys[c].starts(t, st, fit);
      };
      auto score = [&](int c, int t, double p) { return toys[c].score(t, p); };
      auto fit = [&](int c, int t, double p, double r0) { return toys[c].fitFrom(t, p, r0); };
      auto same = [](double p, double q) { return p == q; };
      // fitChains: 12 chains on 4 threads speculate (fitAlongChains), on 2 threads each is a serial
      // chain; the same fits.
      for (int threads : {4, 2}) {
        omp_set_num_threads(threads);
        const std::vector<std::vector<double>> all =
            seg::fitChains(chains, T, ref, 0.0, starts, score, fit, same);
        ASSERT_EQ(all.size(), static_cast<std::size_t>(chains));
        for (int c = 0; c < chains; ++c)
          EXPECT_EQ(all[c], toys[c].run(ref, false)) << "chain " << c << " threads " << threads;
      }
      omp_set_num_threads(4);
      // With 0 to 8 parallel rounds before the serial check (the default on 4 threads: 6).
      for (int rounds : {0, 1, 3, 8, -1}) {
        const std::vector<std::vector<double>> all =
            seg::fitAlongChains(chains, T, ref, 0.0, starts, score, fit, same, rounds);
        ASSERT_EQ(all.size(), static_cast<std::size_t>(chains));
        for (int c = 0; c < chains; ++c) {
          const std::vector<double> alone = toys[c].run(ref, false);
          for (int t = 0; t < T; ++t)
            EXPECT_EQ(all[c][t], alone[t])
                << "chain " << c << " ref " << ref << " frame " << t << " rounds " << rounds;
        }
      }
      // fitChainsBatched with the scores and the fits in batches, as a device takes them (each
      // batch scored back to front, to check that the scores are matched to their starts): the
      // serial chains' fits, with and without speculation.
      for (bool speculate : {true, false}) {
        int score_batches = 0;
        std::size_t largest = 0;
        auto scoreBatch = [&](const std::vector<seg::ChainScore<double>>& items) {
          ++score_batches;
          largest = std::max(largest, items.size());
          std::vector<double> out(items.size());
          for (std::size_t i = items.size(); i-- > 0;)
            out[i] = toys[items[i].chain].score(items[i].frame, items[i].pose);
          return out;
        };
        auto fitBatch = [&](const std::vector<seg::ChainFit<double>>& jobs) {
          std::vector<double> out;
          for (const auto& j : jobs)
            out.push_back(toys[j.chain].fitFrom(j.frame, j.start, j.score));
          return out;
        };
        const std::vector<std::vector<double>> all = seg::fitChainsBatched(
            chains, T, ref, 0.0, starts, scoreBatch, fitBatch, same, speculate, 6);
        ASSERT_EQ(all.size(), static_cast<std::size_t>(chains));
        for (int c = 0; c < chains; ++c)
          EXPECT_EQ(all[c], toys[c].run(ref, false)) << "chain " << c << " speculate " << speculate;
        // Speculation scores every frame's unchained starts in one batch.
        if (speculate) {
          EXPECT_GE(largest, static_cast<std::size_t>(2 * chains * (T - 1)));
        }
        EXPECT_GT(score_batches, 0);
        EXPECT_THROW(seg::fitChainsBatched(
                         chains, T, ref, 0.0, starts,
                         [](const std::vector<seg::ChainScore<double>>&) {
                           return std::vector<double>(1, 0.0);
                         },
                         fitBatch, same, speculate, 6),
                     pcl_animseg::Error);
      }
    }
  }
  omp_set_num_threads(before);
  EXPECT_TRUE(seg::fitAlongChains(
                  0, 10, 0, 0.0,
                  [](int, int, const seg::ChainStep&, const std::vector<double>*) {
                    return std::vector<seg::ChainStart<double>>{};
                  },
                  [](int, int, double) { return 0.0; },
                  [](int, int, double, double) { return 0.0; }, [](double, double) { return true; })
                  .empty());
}

// detail::eachIndex: every index once, on several threads where it may, in the caller's thread
// for one index or inside a parallel region (there it must not start a team of its own).
TEST(ChainedFit, EachIndexVisitsEveryIndexOnceAndStaysInTheCallersThread) {
  const int before = omp_get_max_threads();
  omp_set_num_threads(std::max(2, before));
  for (long n : {0L, 1L, 2L, 37L, 1000L}) {
    std::vector<int> visits(static_cast<std::size_t>(n), 0),
        thread(static_cast<std::size_t>(n), -1);
    seg::detail::eachIndex(n, 4, [&](long j) {
      ++visits[j];
      thread[j] = omp_get_thread_num();
    });
    EXPECT_EQ(std::count(visits.begin(), visits.end(), 1), n) << "n " << n;
    if (n == 1) {
      EXPECT_EQ(thread[0], 0);
      EXPECT_FALSE(omp_in_parallel());
    }
  }
  // Inside a parallel region each thread's call runs its indices itself, in its own thread.
  std::vector<int> mismatched(static_cast<std::size_t>(omp_get_max_threads()), 0);
#pragma omp parallel
  {
    const int me = omp_get_thread_num();
    std::vector<int> seen(50, 0);
    seg::detail::eachIndex(50, 1, [&](long j) {
      ++seen[j];
      if (omp_get_thread_num() != me) ++mismatched[me];  // a team of one would renumber it 0
    });
    if (std::count(seen.begin(), seen.end(), 1) != 50) ++mismatched[me];
  }
  EXPECT_EQ(std::count(mismatched.begin(), mismatched.end(), 0),
            static_cast<long>(mismatched.size()));
  omp_set_num_threads(before);
}
