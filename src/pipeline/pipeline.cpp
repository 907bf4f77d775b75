#include <pcl_animseg/error.h>
#include <pcl_animseg/pipeline.h>
#include <pcl_animseg/progress.h>

#include <algorithm>
#include <set>

namespace pcl_animseg {

void validate(const PipelineParams& p) {
  if (!(p.bandwidth > 0.0)) throw Error("bandwidth must be > 0 (got " + std::to_string(p.bandwidth) + ")");
  for (double w : {p.w1, p.w2, p.w3, p.w4})
    if (!(w >= 0.0)) throw Error("weights must be >= 0 (got " + std::to_string(w) + ")");
  if (p.device != "auto" && p.device != "cpu" && p.device != "gpu")
    throw Error("device must be auto, cpu or gpu (got '" + p.device + "')");
  if (p.method != "default" && p.method != "paper")
    throw Error("method must be default or paper (got '" + p.method + "')");
  if (p.levels < 0) throw Error("levels must be >= 0");
}

namespace {
int countLabels(const std::vector<std::vector<int>>& labels) {
  std::set<int> s;
  for (const auto& f : labels)
    for (int l : f)
      if (l >= 0) s.insert(l);
  return static_cast<int>(s.size());
}
}  // namespace

PipelineResult runPipeline(const PointCloudSequence& seq, const PipelineParams& params,
                           Progress& progress) {
  validate(params);
  if (seq.empty()) throw Error("the sequence has no frames");
  PipelineResult r;
  const std::size_t T = seq.size();

  // Stages not built yet are reported, never faked.
  for (const char* s : {"scale_space", "keypoints", "signature", "mean_shift", "refine", "hierarchy",
                        "rigid_motion"})
    r.missing.push_back(s);

  // Without a segmenter every point is in one part: the honest "no decomposition" answer.
  std::vector<std::vector<int>> level0(T);
  for (std::size_t t = 0; t < T; ++t) level0[t].assign(seq.frame(t)->size(), 0);
  r.levels.push_back(level0);
  r.notes.push_back("no segmentation stage in this build: every point is labelled 0");
  for (const auto& l : r.levels) r.parts_per_level.push_back(countLabels(l));
  r.timings = progress.timings();
  return r;
}

}  // namespace pcl_animseg
