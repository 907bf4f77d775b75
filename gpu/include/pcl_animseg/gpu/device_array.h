#pragma once
/** \file device_array.h RAII buffers in GPU memory, shaped like pcl/gpu/containers/device_array.h
 * (`DeviceArray<T>` with `upload` / `download`), with no CUDA type in sight so that any C++
 * translation unit can hold one.
 *
 * Every failing CUDA call throws pcl_animseg::Error with CUDA's own message; an allocation that
 * does not fit says how much was asked and how much is free, so that the caller can fall back to
 * the CPU (`--device auto`) or ask for less.
 */
#include <cstddef>
#include <vector>

namespace pcl_animseg {
namespace gpu {

/** \brief Untyped, move-only block of device memory. Allocations are counted for
 * peakDeviceBytes() (device.h). */
class DeviceMemory {
 public:
  DeviceMemory() = default;
  /** \brief Allocates `bytes` (throws Error when the device is missing or full). */
  explicit DeviceMemory(std::size_t bytes) { create(bytes); }
  ~DeviceMemory() { release(); }
  DeviceMemory(const DeviceMemory&) = delete;
  DeviceMemory& operator=(const DeviceMemory&) = delete;
  DeviceMemory(DeviceMemory&& other) noexcept;
  DeviceMemory& operator=(DeviceMemory&& other) noexcept;

  /** \brief (Re)allocates to exactly `bytes`; keeps the block when the size is unchanged.
   * Contents are undefined afterwards. */
  void create(std::size_t bytes);
  /** \brief Frees the block (never throws). */
  void release() noexcept;
  void uploadBytes(const void* host, std::size_t bytes);
  void downloadBytes(void* host, std::size_t bytes) const;
  /** \brief Sets every byte to zero. */
  void setZero();
  /** \brief Device-to-device copy into `other` (resized to match). */
  void copyTo(DeviceMemory& other) const;

  std::size_t sizeBytes() const { return bytes_; }
  bool empty() const { return bytes_ == 0; }
  void* rawPtr() { return ptr_; }
  const void* rawPtr() const { return ptr_; }

 private:
  void* ptr_ = nullptr;
  std::size_t bytes_ = 0;
};

/** \brief Typed device array of `size()` elements of a trivially copyable T. */
template <typename T>
class DeviceArray : public DeviceMemory {
 public:
  DeviceArray() = default;
  explicit DeviceArray(std::size_t size) { create(size); }
  DeviceArray(const T* host, std::size_t size) { upload(host, size); }

  void create(std::size_t size) { DeviceMemory::create(size * sizeof(T)); }
  /** \brief Allocates `size` elements and copies them from host memory. */
  void upload(const T* host, std::size_t size) {
    create(size);
    uploadBytes(host, size * sizeof(T));
  }
  void upload(const std::vector<T>& host) { upload(host.data(), host.size()); }
  /** \brief Copies all elements to `host`, which must hold size() elements. */
  void download(T* host) const { downloadBytes(host, sizeBytes()); }
  void download(std::vector<T>& host) const {
    host.resize(size());
    download(host.data());
  }

  std::size_t size() const { return sizeBytes() / sizeof(T); }
  T* ptr() { return static_cast<T*>(rawPtr()); }
  const T* ptr() const { return static_cast<const T*>(rawPtr()); }
};

}  // namespace gpu
}  // namespace pcl_animseg
