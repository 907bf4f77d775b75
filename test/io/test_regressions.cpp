// Regression tests: inputs found by the fuzzers (fuzz/) and by the forced-abort test, kept so the
// fixes stay fixed. Each reader must answer a bad file with pcl_animseg::Error, never a crash.
#include <gtest/gtest.h>
#include <pcl/io/pcd_io.h>
#include <pcl/point_types.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/io/atomic_file.h>
#include <pcl_animseg/io/frame_readers.h>
#include <pcl_animseg/io/sequence_io.h>
#include <stdlib.h>
#include <unistd.h>

#include <filesystem>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <iterator>
#include <string>

#include "temp_dir.h"

namespace fs = std::filesystem;
namespace io = pcl_animseg::io;

namespace {

using animseg_test::TempDir;

std::string write(const fs::path& dir, const std::string& name, const std::string& bytes) {
  const fs::path p = dir / name;
  std::ofstream(p, std::ios::binary) << bytes;
  return p.string();
}

}  // namespace

// A writer killed between creating its temporary and the rename (animseg under SIGKILL, see
// test/tools/test_atomic_kill.cpp) leaves `.NAME.tmp.PID`; the next write into that directory
// removes temporaries of dead processes, and only those.
TEST(AtomicWrite, RemovesStaleTemporariesOfDeadProcesses) {
  TempDir tmp;
  // PIDs are at most 2^22 on Linux, so 999999999 is never a live process.
  const std::string dead = write(tmp.dir(), ".f0.labels.tmp.999999999", "1\n2\n");
  const std::string mine =
      write(tmp.dir(), ".f1.labels.tmp." + std::to_string(::getpid()), "partial");
  const std::string other = write(tmp.dir(), ".notes.tmp.txt", "not ours");
  io::writeTextAtomically((tmp.dir() / "summary.json").string(), "{}\n");
  EXPECT_FALSE(fs::exists(dead));
  EXPECT_TRUE(fs::exists(mine));
  EXPECT_TRUE(fs::exists(other));
  EXPECT_TRUE(fs::exists(tmp.dir() / "summary.json"));
}

// fuzz_off: a vertex count beyond size_t was cast before being compared with the file length
// (undefined behaviour; UBSan float-cast-overflow).
TEST(ReaderRegressions, OffCountTooLargeForSizeT) {
  TempDir tmp;
  const std::string p = write(tmp.dir(), "big.off", "OFF\n1e300 0 0\n");
  EXPECT_THROW(io::readOFF(p), pcl_animseg::Error);
  const std::string q = write(tmp.dir(), "faces.off", "OFF\n3 1e300 0\n0 0 0\n1 0 0\n0 1 0\n");
  EXPECT_THROW(io::readOFF(q), pcl_animseg::Error);
}

// fuzz_ply: an element with no properties and a huge count made the reader loop for ever.
TEST(ReaderRegressions, PlyElementWithoutPropertiesAndHugeCount) {
  TempDir tmp;
  const std::string p = write(tmp.dir(), "loop.ply",
                              "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"
                              "property float y\nproperty float z\n"
                              "element junk 1000000000000000\nend_header\n1 2 3\n");
  const io::RawFrame raw = io::readPLY(p);  // the empty element holds no data: nothing to skip
  ASSERT_EQ(raw.points.size(), 1u);
  EXPECT_FLOAT_EQ(raw.points[0].z(), 3.0f);
}

// fuzz_ply (UBSan): a face index of 8.9e34 was cast to long long for the error message, which is
// undefined; the message now shows the number as read.
TEST(ReaderRegressions, PlyHugeFaceIndexIsReportedAsRead) {
  TempDir tmp;
  const std::string p = write(tmp.dir(), "face.ply",
                              "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                              "property float y\nproperty float z\nelement face 1\n"
                              "property list uchar int vertex_indices\nend_header\n"
                              "0 0 0\n1 0 0\n0 1 0\n3 0 1 88888888888888888888888888888888882\n");
  try {
    io::readPLY(p);
    FAIL() << "no error";
  } catch (const pcl_animseg::Error& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("refers to vertex 8.88889e+34"), std::string::npos) << what;
  }
}

// fuzz_pcd: WIDTH x HEIGHT and SIZE x COUNT overflowed `long` in the header check (UBSan
// signed-integer-overflow), and a wrapped size would have let PCL trust the header.
TEST(ReaderRegressions, PcdHeaderProductsOverflow) {
  TempDir tmp;
  const std::string head = "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\n";
  for (const std::string& rest :
       {std::string("WIDTH 4294967296\nHEIGHT 4294967296\nPOINTS 1\nDATA binary\n"),
        std::string("WIDTH 9223372036854775807\nHEIGHT 2\nDATA binary\n"),
        std::string("COUNT 1 1 4611686018427387904\nWIDTH 1\nHEIGHT 1\nDATA binary\n"),
        std::string("WIDTH 4294967295\nHEIGHT 4294967295\nDATA ascii\n1 2 3\n")}) {
    const std::string p = write(tmp.dir(), "bad.pcd", head + rest);
    EXPECT_THROW(io::readPCD(p), pcl_animseg::Error) << rest;
  }
}

// fuzz_pcd: a non-integer WIDTH given twice made PCL's own reader allocate ~100 TB (ASan abort).
TEST(ReaderRegressions, PcdHeaderCountsMustBeWholeAndGivenOnce) {
  TempDir tmp;
  const std::string head = "VERSION 01\nFIELDS x y z label\nSIZE 8 8 8 4\nTYPE F F F U\n";
  const std::string data(4 * 28, '\0');
  for (const std::string& rest :
       {std::string("WIDTH 4.7\nCOUNT 1 1 1 1\nWIDTH 2\nHEIGHT 2\nPOINTS 4\nDATA binary\n"),
        std::string("WIDTH 2\nHEIGHT 2\nHEIGHT 2\nPOINTS 4\nDATA binary\n"),
        std::string("WIDTH 4 4\nHEIGHT 1\nDATA binary\n")}) {
    const std::string p = write(tmp.dir(), "bad.pcd", head + rest + data);
    EXPECT_THROW(io::readPCD(p), pcl_animseg::Error) << rest;
  }
  // The same header with whole counts given once is read.
  const std::string p =
      write(tmp.dir(), "good.pcd", head + "WIDTH 2\nHEIGHT 2\nPOINTS 4\nDATA binary\n" + data);
  EXPECT_NO_THROW(io::readPCD(p));
}

// A binary PCD whose header and length are valid and whose data bytes are arbitrary (found by
// fuzz_pcd): PCL's reader crashed (SIGSEGV) on it; binary data is now read by us. The points are
// read as they are (a few finite ones, the rest NaN or huge), and the values round-trip.
TEST(ReaderRegressions, BinaryPcdDataIsReadWithoutPcl) {
  const std::string crash =
      std::string(PCL_ANIMSEG_SOURCE_DIR) + "/fuzz/corpus/pcd/regression-binary-data.pcd";
  EXPECT_NO_THROW(io::readPCD(crash));
  // x y z as doubles, a uint label, 2 x 2 points: the values come back exactly.
  TempDir tmp;
  std::string data;
  auto put = [&](const void* v, std::size_t n) { data.append(static_cast<const char*>(v), n); };
  for (int i = 0; i < 4; ++i) {
    const double xyz[3] = {0.5 * i, -1.25 * i, 3.0 + i};
    const std::uint32_t label = 7u + static_cast<std::uint32_t>(i);
    put(xyz, sizeof(xyz));
    put(&label, sizeof(label));
  }
  const std::string p = write(tmp.dir(), "doubles.pcd",
                              "VERSION 0.7\nFIELDS x y z label\nSIZE 8 8 8 4\nTYPE F F F U\n"
                              "COUNT 1 1 1 1\nWIDTH 2\nHEIGHT 2\nPOINTS 4\nDATA binary\n" +
                                  data);
  const io::RawFrame raw = io::readPCD(p);
  ASSERT_EQ(raw.points.size(), 4u);
  // A 1-byte float field (found by fuzz_pcd: PCL's reader segfaulted on it) is a header error.
  const std::string tiny = write(tmp.dir(), "tiny_float.pcd",
                                 "VERSION 0.7\nFIELDS x y z\nSIZE 1 4 4\nTYPE F F F\n"
                                 "WIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n0 0 0\n");
  EXPECT_THROW(io::readPCD(tiny), pcl_animseg::Error);
  for (int i = 0; i < 4; ++i) {
    EXPECT_FLOAT_EQ(raw.points[i].x(), 0.5f * i);
    EXPECT_FLOAT_EQ(raw.points[i].y(), -1.25f * i);
    EXPECT_FLOAT_EQ(raw.points[i].z(), 3.0f + i);
  }
}

// ASCII PCD data lines are checked before PCL parses them (found by fuzz_pcd: PCL's ASCII reader
// went out of bounds on data lines holding other tokens): each point one line of exactly the
// header's number of values, every value a number.
TEST(ReaderRegressions, AsciiPcdDataLinesAreChecked) {
  TempDir tmp;
  const std::string head =
      "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\n"
      "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA ascii\n";
  for (const std::string& body : {std::string("VERSION 0.7\nFIELDS\n0 0 0\n1 1 1\n"),
                                  std::string("0 0 0\n1 1\n"), std::string("0 0 0 0\n1 1 1\n"),
                                  std::string("0 0 0\n"), std::string("0 0 0\n1 1 1\n2 2 2\n")}) {
    const std::string p = write(tmp.dir(), "bad.pcd", head + body);
    EXPECT_THROW(io::readPCD(p), pcl_animseg::Error) << body;
  }
  const io::RawFrame raw =
      io::readPCD(write(tmp.dir(), "good.pcd", head + "0 0 0\n1 nan 2.5\n"));
  ASSERT_EQ(raw.points.size(), 2u);
  EXPECT_FLOAT_EQ(raw.points[1].z(), 2.5f);
  EXPECT_TRUE(std::isnan(raw.points[1].y()));
  EXPECT_THROW(io::readPCD(std::string(PCL_ANIMSEG_SOURCE_DIR) +
                           "/fuzz/corpus/pcd/regression-ascii-bad-lines.pcd"),
               pcl_animseg::Error);
}

// An ASCII PCD whose header has a blank-only line before VERSION (found by fuzz_pcd: PCL's
// reader segfaulted on it). ASCII data is now read by us from the checked lines: the file is a
// valid PCD (comments and blank lines are allowed), so its four points come back exactly, and
// an organised ASCII cloud with a multi-value field keeps its point order.
TEST(ReaderRegressions, AsciiPcdIsReadWithoutPcl) {
  const io::RawFrame crash = io::readPCD(std::string(PCL_ANIMSEG_SOURCE_DIR) +
                                         "/fuzz/corpus/pcd/regression-blank-header-line.pcd");
  ASSERT_EQ(crash.points.size(), 4u);
  ASSERT_EQ(crash.normals.size(), 4u);
  EXPECT_FLOAT_EQ(crash.points[3].x(), 1.0f);
  EXPECT_FLOAT_EQ(crash.points[3].y(), 1.0f);
  EXPECT_FLOAT_EQ(crash.points[3].z(), 0.5f);
  EXPECT_FLOAT_EQ(crash.normals[3].z(), 1.0f);
  TempDir tmp;
  const io::RawFrame raw = io::readPCD(
      write(tmp.dir(), "organised.pcd",
            "VERSION 0.7\nFIELDS rgb x y z label\nSIZE 4 4 4 4 4\nTYPE U F F F I\n"
            "COUNT 2 1 1 1 1\nWIDTH 2\nHEIGHT 2\nPOINTS 4\nDATA ascii\n"
            "9 9 0 0 0 1\n9 9 1 0 0 2\n9 9 0 1 0 3\n9 9 0.25 -2 7 4\n"));
  ASSERT_EQ(raw.points.size(), 4u);
  EXPECT_TRUE(raw.normals.empty());
  EXPECT_FLOAT_EQ(raw.points[1].x(), 1.0f);
  EXPECT_FLOAT_EQ(raw.points[3].x(), 0.25f);
  EXPECT_FLOAT_EQ(raw.points[3].y(), -2.0f);
  EXPECT_FLOAT_EQ(raw.points[3].z(), 7.0f);
  // Other fields keep their declared types (a label written as uint32 max stays all ones, a
  // negative int stays negative, an out-of-range value is clamped).
  const pcl::PCLPointCloud2 blob = io::readPCDCloud(
      write(tmp.dir(), "typed.pcd",
            "VERSION 0.7\nFIELDS x y z label i\nSIZE 4 4 4 4 1\nTYPE F F F U I\nCOUNT 1 1 1 1 1\n"
            "WIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA ascii\n0 0 0 4294967295 -3\n1 1 1 7 500\n"));
  ASSERT_EQ(blob.fields.size(), 5u);
  std::uint32_t label[2];
  std::int8_t small[2];
  for (int i = 0; i < 2; ++i) {
    std::memcpy(&label[i], &blob.data[i * blob.point_step + blob.fields[3].offset], 4);
    std::memcpy(&small[i], &blob.data[i * blob.point_step + blob.fields[4].offset], 1);
  }
  EXPECT_EQ(label[0], 4294967295u);
  EXPECT_EQ(label[1], 7u);
  EXPECT_EQ(small[0], -3);
  EXPECT_EQ(small[1], 127);
}

// binary_compressed PCD data is read by us too (PCL's lzfDecompress, then the field columns
// copied into point records), so that no PCD data goes through PCL's parser, which fuzz_pcd found
// crashing on six kinds of input: a file PCL wrote comes back exactly, one whose compressed bytes
// are damaged is one clear error.
TEST(ReaderRegressions, CompressedPcdIsReadWithoutPcl) {
  TempDir tmp;
  pcl::PointCloud<pcl::PointNormal> cloud;
  for (int i = 0; i < 50; ++i) {
    pcl::PointNormal p;
    p.x = 0.1f * i;
    p.y = -0.2f * i;
    p.z = 1.0f + 0.01f * i * i;
    p.normal_x = 0.0f;
    p.normal_y = (i % 2) ? 1.0f : -1.0f;
    p.normal_z = 0.0f;
    p.curvature = 0.5f;
    cloud.push_back(p);
  }
  const std::string path = (std::filesystem::path(tmp.dir()) / "packed.pcd").string();
  ASSERT_EQ(pcl::io::savePCDFileBinaryCompressed(path, cloud), 0);
  const io::RawFrame raw = io::readPCD(path);
  ASSERT_EQ(raw.points.size(), cloud.size());
  ASSERT_EQ(raw.normals.size(), cloud.size());
  for (std::size_t i = 0; i < cloud.size(); ++i) {
    EXPECT_FLOAT_EQ(raw.points[i].x(), cloud[i].x);
    EXPECT_FLOAT_EQ(raw.points[i].y(), cloud[i].y);
    EXPECT_FLOAT_EQ(raw.points[i].z(), cloud[i].z);
    EXPECT_FLOAT_EQ(raw.normals[i].y(), cloud[i].normal_y);
  }
  // Damage the compressed bytes (after the header and the two sizes): the LZF stream no longer
  // decodes to the announced size.
  std::string bytes;
  {
    std::ifstream in(path, std::ios::binary);
    bytes.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  }
  const std::size_t data = bytes.find("DATA binary_compressed\n") + 23 + 8;
  ASSERT_LT(data + 4, bytes.size());
  for (std::size_t i = data; i < bytes.size(); ++i) bytes[i] = static_cast<char>(0xE0);
  const std::string bad = write(tmp.dir(), "damaged.pcd", bytes);
  EXPECT_THROW(io::readPCD(bad), pcl_animseg::Error);
  // Sizes that announce far more data than LZF can expand the payload to (1.2 GB from 10
  // bytes) are an error before anything of that size is allocated.
  std::string huge =
      "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 100000000\n"
      "HEIGHT 1\nPOINTS 100000000\nDATA binary_compressed\n";
  const std::uint32_t sizes[2] = {10u, 1200000000u};
  huge.append(reinterpret_cast<const char*>(sizes), sizeof(sizes));
  huge.append(10, '\x01');
  EXPECT_THROW(io::readPCD(write(tmp.dir(), "huge.pcd", huge)), pcl_animseg::Error);
  // The fuzz seed (four points, written by PCL) reads too.
  EXPECT_EQ(io::readPCD(std::string(PCL_ANIMSEG_SOURCE_DIR) + "/fuzz/corpus/pcd/compressed.pcd")
                .points.size(),
            4u);
}

