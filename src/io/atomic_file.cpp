#include <pcl_animseg/error.h>
#include <pcl_animseg/io/atomic_file.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <system_error>

namespace pcl_animseg {
namespace io {

namespace fs = std::filesystem;

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
