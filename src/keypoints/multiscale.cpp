#include <pcl_animseg/error.h>
#include <pcl_animseg/features/multiscale.h>
#include <pcl_animseg/features/scale_space.h>
#include <pcl_animseg/keypoints/dog_keypoint.h>
#include <pcl_animseg/progress.h>

#include <algorithm>
#include <cmath>
#include <map>
#include <string>
#include <vector>

#include <omp.h>

namespace pcl_animseg {
namespace {

/** Runs `work(t)` for every frame t as one Progress stage. With at least as many frames as
 * threads, the frames run in parallel (one OpenMP region per stage; the per-point regions inside
 * then run on one thread): a frame of ~17k points is too little work to share between threads
 * point by point, 16 diffusion steps and 2 more passes per frame cost a team barrier each, and on
 * a loaded machine the threads spent a third of their time waiting in them. With fewer frames
 * (a single frame from a tool), frames run one after the other, parallel over points inside.
 * Errors name the frame; when several frames fail, the first frame's error is thrown. */
template <typename Work, typename Detail, typename Finish>
void forEachFrame(const PointCloudSequence& seq, std::size_t first, std::size_t last,
                  Progress* progress, const char* stage, Work work, Detail detail, Finish finish) {
  const std::size_t T = last - first;
  if (progress) progress->begin(stage, T);
  std::vector<std::string> errors(T);
  std::vector<char> failed(T, 0);  // 1: the frame's error, 2: its device's (DeviceError)
  auto runOne = [&](std::size_t i) {
    const std::size_t t = first + i;
    try {
      work(t);
    } catch (const DeviceError& e) {
      // Not the frame's: said and thrown as it is, so that the pipeline can tell it from the
      // input's.
      errors[i] = e.what();
      failed[i] = 2;
    } catch (const std::exception& e) {
      errors[i] = "frame '" + seq.name(t) + "': " + e.what();
      failed[i] = 1;
    }
  };
  const int threads = omp_get_max_threads();
  if (threads > 1 && T >= static_cast<std::size_t>(threads) && !omp_in_parallel()) {
    std::size_t done = 0;
#pragma omp parallel for schedule(dynamic, 1)
    for (long tl = 0; tl < static_cast<long>(T); ++tl) {
      runOne(static_cast<std::size_t>(tl));
      std::size_t now;
#pragma omp atomic capture
      now = ++done;
      if (progress && omp_get_thread_num() == 0) progress->update(now);
    }
  } else {
    for (std::size_t t = 0; t < T; ++t) {
      runOne(t);
      if (progress) progress->update(t + 1);
    }
  }
  for (std::size_t t = 0; t < T; ++t) {
    if (failed[t] == 2) throw DeviceError(errors[t]);
    if (failed[t]) throw Error(errors[t]);
  }
  finish();
  if (progress) {
    progress->update(T);
    progress->end(detail());
  }
}

template <typename Work, typename Detail>
void forEachFrame(const PointCloudSequence& seq, std::size_t first, std::size_t last,
                  Progress* progress, const char* stage, Work work, Detail detail) {
  forEachFrame(seq, first, last, progress, stage, work, detail, [] {});
}

void computeBlock(const PointCloudSequence& seq, std::size_t first, std::size_t last,
                  const MultiscaleParams& p, double unit, std::vector<ScaleSpace>& spaces,
                  std::vector<std::size_t>& kp_count, SequenceFeatures& out, Progress* progress,
                  FeatureDevice* device);

}  // namespace

SequenceFeatures computeSequenceFeatures(const PointCloudSequence& seq, const MultiscaleParams& p,
                                         Progress* progress, FeatureDevice* device) {
  if (seq.empty()) throw Error("the sequence has no frames");
  p.layout.validate();
  if (!(p.signature_h > 0.0)) throw Error("the signature scale must be positive");
  const bool detect = p.detect_keypoints;
  if (detect && p.levels < 4)
    throw Error("keypoint detection needs at least 4 levels (got " + std::to_string(p.levels) +
                ")");
  const std::size_t T = seq.size();
  SequenceFeatures out;
  out.signatures.resize(T);
  out.keypoints.resize(T);
  out.keypoint_scale.resize(T);
  out.keypoint_response.resize(T);
  if (p.keep_smoothed) out.smoothed.resize(T);

  // Stage by stage over a block of frames, so that Progress records the three stages of
  // DESIGN.md's summary (a stage's time is summed over blocks). A frame's scale space (levels and
  // neighbour lists, ~500 bytes a point) lives only while its block runs, so memory grows with the
  // block, not with the sequence; the levels above 0 are released as soon as the keypoints are
  // found.
  if (p.block_points == 0) throw Error("the feature block size must be at least one point");
  std::vector<ScaleSpace> spaces(T);
  const double unit = sequenceSpacing(seq);
  std::vector<std::size_t> kp_count(T, 0);
  for (std::size_t first = 0; first < T;) {
    std::size_t last = first, points = 0;
    while (last < T && (last == first || points + seq.frame(last)->size() <= p.block_points))
      points += seq.frame(last++)->size();
    computeBlock(seq, first, last, p, unit, spaces, kp_count, out, progress, device);
    first = last;
  }
  return out;
}

namespace {

void computeBlock(const PointCloudSequence& seq, std::size_t first, std::size_t last,
                  const MultiscaleParams& p, double unit, std::vector<ScaleSpace>& spaces,
                  std::vector<std::size_t>& kp_count, SequenceFeatures& out, Progress* progress,
                  FeatureDevice* device) {
  const bool detect = p.detect_keypoints;

  // Stage 1: scale space of every frame (on the device: the frames are checked here, then the
  // device computes the block's levels and signatures).
  std::vector<ScaleSpacePlan> plans(device ? last - first : 0);
  forEachFrame(
      seq, first, last, progress, "scale_space",
      [&](std::size_t t) {
        MLSScaleSpace mls;
        configureScaleSpace(mls, seq.frame(t), p, unit);
        if (device)
          plans[t - first] = mls.plan();
        else
          mls.compute(spaces[t]);
      },
      [&] { return std::to_string(p.levels) + " levels" + (device ? " (GPU)" : ""); },
      [&] {
        if (device) device->scaleSpaces(seq, first, last, plans, p, detect, spaces);
      });

  // Stage 2: keypoints.
  forEachFrame(
      seq, first, last, progress, "keypoints",
      [&](std::size_t t) {
        if (detect) {
          DoGKeypoint dog;
          dog.setScaleSpace(spaces[t]);
          dog.setMinResponse(p.min_response);
          dog.setEdgeRatio(p.edge_ratio);
          if (device) dog.setRefineDevice(device->keypointRefiner());
          DoGKeypoint::KeypointCloud kps;
          dog.compute(kps);
          std::map<int, std::size_t> best;  // index -> keypoint with the largest |response|
          for (std::size_t a = 0; a < kps.size(); ++a) {
            auto it = best.find(kps[a].index);
            if (it == best.end() ||
                std::fabs(kps[a].response) > std::fabs(kps[it->second].response))
              best[kps[a].index] = a;
          }
          for (const auto& kv : best) {
            out.keypoints[t].push_back(kv.first);
            out.keypoint_scale[t].push_back(kps[kv.second].scale);
            out.keypoint_response[t].push_back(kps[kv.second].response);
          }
          kp_count[t] = best.size();
        }
        spaces[t].levels.resize(1);
      },
      [&] {
        std::size_t total_kp = 0;
        for (std::size_t c : kp_count) total_kp += c;
        return std::to_string(total_kp) + " keypoints";
      });

  // Stage 3: signatures.
  forEachFrame(
      seq, first, last, progress, "signature",
      [&](std::size_t t) {
        if (device) {
          device->signature(t, out.signatures[t]);
        } else {
          SignatureEstimation se;
          se.setInputCloud(signatureInput(*seq.frame(t), *spaces[t].levels[0]));
          se.setNeighbourhoods(spaces[t].neighbourhoods);
          se.setScale(p.signature_h * spaces[t].spacing);
          se.setLayout(p.layout);
          se.setKeypoints(out.keypoints[t]);
          se.compute(out.signatures[t]);
        }
        if (p.keep_smoothed) out.smoothed[t] = spaces[t].levels[0];
        spaces[t] = ScaleSpace();
      },
      [&] { return std::to_string(p.layout.dimension()) + "-D"; });
}

}  // namespace

}  // namespace pcl_animseg
