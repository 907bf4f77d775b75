#pragma once
/** \file packed_vector.h A vector whose resize leaves new elements of trivial types
 * uninitialised, for buffers that are written whole (or as far as they are read) right after. */
#include <memory>
#include <utility>
#include <vector>

namespace pcl_animseg {

/** \brief An allocator whose resize leaves new elements of trivial types uninitialised: a
 * zeroing pass over a buffer that is written next costs a serial pass over memory touched for
 * the first time (the GPU module's packed frames: a third of their packing; the motion method's
 * error columns: 7-11 ms of the 800k part merges' main thread). Used by nvcc too: no Eigen. */
template <class T>
struct NoInitAllocator : std::allocator<T> {
  template <class U>
  struct rebind {
    using other = NoInitAllocator<U>;
  };
  NoInitAllocator() = default;
  template <class U>
  NoInitAllocator(const NoInitAllocator<U>&) noexcept {}
  template <class U>
  void construct(U* p) noexcept {
    ::new (static_cast<void*>(p)) U;
  }
  template <class U, class... Args>
  void construct(U* p, Args&&... args) {
    ::new (static_cast<void*>(p)) U(std::forward<Args>(args)...);
  }
};

/** \brief std::vector with NoInitAllocator: resize() leaves new elements as they are. */
template <class T>
using PackedVector = std::vector<T, NoInitAllocator<T>>;

}  // namespace pcl_animseg
