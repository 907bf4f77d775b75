#pragma once
// Shared harness for the reader fuzzers: the readers take paths, so each input is written to a
// file in a per-process temporary directory and the reader is called on it. pcl_animseg::Error is
// the expected outcome for bad input; any other exception aborts (a finding), as do crashes and
// sanitizer reports.
#include <pcl_animseg/error.h>
#include <unistd.h>

#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <filesystem>
#include <fstream>
#include <string>

namespace fuzz {

/** A private directory, created once per process and removed at exit. The path lives on the heap
 *  and is never destroyed: a function-local static path would be destroyed before the atexit
 *  handler registered during its own construction runs (exit runs them in reverse order), and the
 *  handler would then remove nothing. */
inline const std::filesystem::path& workDir() {
  static const std::filesystem::path* const dir = [] {
    std::string tmpl = (std::filesystem::temp_directory_path() / "animseg_fuzz_XXXXXX").string();
    if (!mkdtemp(tmpl.data())) {
      std::perror("mkdtemp");
      std::abort();
    }
    auto* path = new std::filesystem::path(tmpl);
    std::atexit([] {
      std::error_code ec;
      std::filesystem::remove_all(workDir(), ec);
    });
    return path;
  }();
  return *dir;
}

/** Writes `data` to workDir()/name and returns the path. */
inline std::string writeInput(const std::uint8_t* data, std::size_t size, const std::string& name) {
  const std::string path = (workDir() / name).string();
  std::ofstream f(path, std::ios::binary | std::ios::trunc);
  f.write(reinterpret_cast<const char*>(data), static_cast<std::streamsize>(size));
  f.close();
  if (!f) {
    std::perror("writing the fuzz input");
    std::abort();
  }
  return path;
}

/** Runs `body`; Error is fine, anything else is reported and aborts. */
template <typename F>
void expectOnlyErrors(F&& body) {
  try {
    body();
  } catch (const pcl_animseg::Error&) {
  } catch (const std::exception& e) {
    std::fprintf(stderr, "fuzz: unexpected exception (not pcl_animseg::Error): %s\n", e.what());
    std::abort();
  } catch (...) {
    std::fprintf(stderr, "fuzz: unexpected non-std exception\n");
    std::abort();
  }
}

}  // namespace fuzz
