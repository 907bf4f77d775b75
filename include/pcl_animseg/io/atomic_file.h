#pragma once
/** \file atomic_file.h Outputs appear whole or not at all (temp file in the same directory +
 * rename). */
#include <functional>
#include <string>

namespace pcl_animseg {
namespace io {

/** \brief Calls `write(tmp_path)` with a temporary path next to `path` (`DIR/.NAME.tmp.PID`:
 * same file system, so the rename is atomic; hidden, so listSequence skips it), then renames it
 * onto `path`, replacing an existing file. On any exception the temporary file is removed and the
 * exception rethrown, so a reader never sees a half-written file and an old file survives a
 * failed rewrite. Throws Error when the directory does not exist, `write` produced no file, or
 * the rename fails. Two threads of one process must not write the same `path` at once. */
void writeAtomically(const std::string& path, const std::function<void(const std::string&)>& write);

/** \brief Writes a text file atomically. */
void writeTextAtomically(const std::string& path, const std::string& content);

/** \brief Creates a directory (and parents); throws pcl_animseg::Error when it can't. */
void ensureDirectory(const std::string& path);

}  // namespace io
}  // namespace pcl_animseg
