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

}  // namespace pcl_animseg
