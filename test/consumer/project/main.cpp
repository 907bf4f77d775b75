// A downstream program: builds against the installed pcl_animseg and uses it.
#include <pcl_animseg/evaluation/metrics.h>
#include <pcl_animseg/sequence.h>

#include <iostream>

int main() {
  pcl_animseg::PointCloudSequence seq;
  std::vector<int> a{0, 0, 1, 1}, b{5, 5, 7, 7};
  const double ari = pcl_animseg::evaluation::adjustedRandIndex(a, b);
  std::cout << "frames " << seq.size() << " ari " << ari << std::endl;
  return ari > 0.999 ? 0 : 1;
}
