#pragma once
/** \file error.h The one exception type of the library: tools print its message as `error: ...`. */
#include <stdexcept>
#include <string>

namespace pcl_animseg {

/** \brief Thrown for anything a user can fix: bad input, bad parameters, an unwritable output. */
class Error : public std::runtime_error {
 public:
  explicit Error(const std::string& what) : std::runtime_error(what) {}
};

/** \brief An Error of a device (the CUDA module's GPU): none usable, out of its memory, a kernel
 * or transfer that failed, or a job beyond its limits. Every error the CUDA module throws is one,
 * so that a caller tells them from the input's own errors by type: with `--device auto` the
 * features fall back to the CPU on these alone (a frame's error is the frame's, whatever ran
 * it); the later stages fall back on any error of their device run. */
class DeviceError : public Error {
 public:
  explicit DeviceError(const std::string& what) : Error(what) {}
};

}  // namespace pcl_animseg
