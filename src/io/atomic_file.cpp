#include <pcl_animseg/error.h>
#include <pcl_animseg/io/atomic_file.h>
#include <signal.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <set>
#include <system_error>

namespace pcl_animseg {
namespace io {

namespace fs = std::filesystem;

namespace {

/** Removes `dir/.NAME.tmp.PID` files whose process no longer exists: what a writer killed between
 * creating its temporary and the rename leaves behind (SIGKILL, power loss). Such files are hidden
 * and never have a final name, but would pile up over reruns into the same directory. A temporary
 * of a live process (a concurrent writer, or a reused PID) is left alone. Each directory is swept
 * once per process (a sweep per write would be quadratic in the number of outputs). */
void removeStaleTemporaries(const fs::path& dir) {
  static std::mutex mutex;
  static std::set<std::string> swept;
  std::error_code ec;
  const std::string key = fs::absolute(dir, ec).lexically_normal().string();
  {
    std::lock_guard<std::mutex> lock(mutex);
    if (!swept.insert(key).second) return;
  }
  for (fs::directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) {
    const std::string f = it->path().filename().string();
    const std::size_t mark = f.rfind(".tmp.");
    if (f.size() < 2 || f[0] != '.' || mark == std::string::npos || mark == 0) continue;
    const std::string digits = f.substr(mark + 5);
    if (digits.empty() || digits.size() > 9 ||
        digits.find_first_not_of("0123456789") != std::string::npos)
      continue;
    const long pid = std::stol(digits);
    if (pid == static_cast<long>(::getpid())) continue;
    if (::kill(static_cast<pid_t>(pid), 0) != 0 && errno == ESRCH) {
      std::error_code rm;
      fs::remove(it->path(), rm);
    }
  }
}

}  // namespace

void writeAtomically(const std::string& path,
                     const std::function<void(const std::string&)>& write) {
  if (path.empty()) throw Error("cannot write a file with an empty name");
  const fs::path target(path);
  const std::string name = target.filename().string();
  if (name.empty() || name == "." || name == "..")
    throw Error("cannot write '" + path + "': it names a directory, not a file");
  // The temporary file lives in the target's directory: rename() is atomic only within one file
  // system, and a hidden name keeps it out of directory listings (listSequence skips dot files).
  const fs::path tmp =
      target.parent_path() / ("." + name + ".tmp." + std::to_string(static_cast<long>(::getpid())));
  const std::string tmp_str = tmp.string();
  {
    std::error_code ec;
    const fs::path dir = target.parent_path().empty() ? fs::path(".") : target.parent_path();
    if (!fs::is_directory(dir, ec))
      throw Error("cannot write '" + path + "': directory '" + dir.string() + "' does not exist");
    removeStaleTemporaries(dir);
  }
  try {
    write(tmp_str);
    std::error_code ec;
    if (!fs::exists(tmp, ec))
      throw Error("cannot write '" + path + "': the writer produced no file");
    if (std::rename(tmp_str.c_str(), path.c_str()) != 0)
      throw Error("cannot write '" + path + "': rename from '" + tmp_str +
                  "' failed: " + std::strerror(errno));
  } catch (...) {
    std::error_code ec;
    fs::remove(tmp, ec);
    throw;
  }
}

void writeTextAtomically(const std::string& path, const std::string& content) {
  writeAtomically(path, [&](const std::string& tmp) {
    std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
    if (!out)
      throw Error("cannot write '" + path + "': cannot create '" + tmp +
                  "': " + std::strerror(errno));
    out.write(content.data(), static_cast<std::streamsize>(content.size()));
    out.close();
    if (!out) throw Error("cannot write '" + path + "': write failed (disk full?)");
  });
}

void ensureDirectory(const std::string& path) {
  if (path.empty()) throw Error("empty output directory name");
  std::error_code ec;
  const fs::path p(path);
  if (fs::exists(p, ec)) {
    if (!fs::is_directory(p, ec)) throw Error("'" + path + "' exists and is not a directory");
    return;
  }
  fs::create_directories(p, ec);
  if (ec || !fs::is_directory(p))
    throw Error("cannot create directory '" + path +
                "': " + (ec ? ec.message() : std::string("unknown error")));
}

}  // namespace io
}  // namespace pcl_animseg
