#include <pcl_animseg/error.h>
#include <pcl_animseg/features/multiscale.h>
#include <pcl_animseg/features/scale_space.h>
#include <pcl_animseg/keypoints/dog_keypoint.h>
#include <pcl_animseg/progress.h>

#include <cmath>
#include <algorithm>
#include <map>

namespace pcl_animseg {

SequenceFeatures computeSequenceFeatures(const PointCloudSequence& seq, const MultiscaleParams& p,
                                         Progress* progress) {
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

  // Stage by stage over all frames, so that Progress records the three stages of DESIGN.md's
  // summary; the levels above 0 are released as soon as the keypoints are found.
  std::vector<ScaleSpace> spaces(T);
  const double unit = sequenceSpacing(seq);
  auto frameError = [&](std::size_t t, const Error& e) {
    return Error("frame '" + seq.name(t) + "': " + e.what());
  };
  if (progress) progress->begin("scale_space", T);
  for (std::size_t t = 0; t < T; ++t) {
    try {
      MLSScaleSpace mls;
      mls.setInputCloud(seq.frame(t));
      mls.setScale(p.h);
      mls.setScaleFactor(p.k);
      mls.setNumberOfLevels(p.levels);
      mls.setNeighbourhoodRadius(2.0 * p.signature_h);
      mls.setSpacing(unit);
      mls.compute(spaces[t]);
    } catch (const Error& e) {
      throw frameError(t, e);
    }
    if (progress) progress->update(t + 1);
  }
  if (progress) progress->end(std::to_string(p.levels) + " levels");

  std::size_t total_kp = 0;
  if (progress) progress->begin("keypoints", T);
  for (std::size_t t = 0; t < T; ++t) {
    if (detect) {
      try {
        DoGKeypoint dog;
        dog.setScaleSpace(spaces[t]);
        dog.setMinResponse(p.min_response);
        dog.setEdgeRatio(p.edge_ratio);
        DoGKeypoint::KeypointCloud kps;
        dog.compute(kps);
        std::map<int, std::size_t> best;  // index -> keypoint with the largest |response|
        for (std::size_t a = 0; a < kps.size(); ++a) {
          auto it = best.find(kps[a].index);
          if (it == best.end() || std::fabs(kps[a].response) > std::fabs(kps[it->second].response))
            best[kps[a].index] = a;
        }
        for (const auto& kv : best) {
          out.keypoints[t].push_back(kv.first);
          out.keypoint_scale[t].push_back(kps[kv.second].scale);
          out.keypoint_response[t].push_back(kps[kv.second].response);
        }
        total_kp += best.size();
      } catch (const Error& e) {
        throw frameError(t, e);
      }
    }
    spaces[t].levels.resize(1);
    if (progress) progress->update(t + 1);
  }
  if (progress) progress->end(std::to_string(total_kp) + " keypoints");

  if (progress) progress->begin("signature", T);
  for (std::size_t t = 0; t < T; ++t) {
    try {
      SignatureEstimation se;
      se.setInputCloud(signatureInput(*seq.frame(t), *spaces[t].levels[0]));
      se.setNeighbourhoods(spaces[t].neighbourhoods);
      se.setScale(p.signature_h * spaces[t].spacing);
      se.setLayout(p.layout);
      se.setKeypoints(out.keypoints[t]);
      se.compute(out.signatures[t]);
    } catch (const Error& e) {
      throw frameError(t, e);
    }
    if (p.keep_smoothed) out.smoothed[t] = spaces[t].levels[0];
    spaces[t] = ScaleSpace();
    if (progress) progress->update(t + 1);
  }
  if (progress) progress->end(std::to_string(p.layout.dimension()) + "-D");
  return out;
}

}  // namespace pcl_animseg
