// The HDF5 user-block seal (core/h5_seal.h): size + CRC-32 of the bytes after the
// block, as text, so `head -c 512 file.h5` shows it.
#include "core/h5_seal.h"

#include <array>
#include <cinttypes>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <vector>

#include "core/error.h"
#include "core/isolated.h"

namespace mc {
namespace {

constexpr const char* kMagic = "motionctl-h5-seal 1\n";

const std::array<uint32_t, 256>& crc_table() {
  static const std::array<uint32_t, 256> table = [] {
    std::array<uint32_t, 256> t{};
    for (uint32_t i = 0; i < 256; ++i) {
      uint32_t c = i;
      for (int k = 0; k < 8; ++k) c = (c & 1) ? 0xEDB88320u ^ (c >> 1) : c >> 1;
      t[i] = c;
    }
    return t;
  }();
  return table;
}

// CRC-32 of the file from byte kH5SealBlock to the end; also returns the size.
uint32_t body_crc(std::ifstream& in, uint64_t& size) {
  in.seekg(0, std::ios::end);
  size = static_cast<uint64_t>(in.tellg());
  in.seekg(kH5SealBlock);
  std::vector<char> buf(1 << 20);
  uint32_t crc = 0;
  while (in) {
    in.read(buf.data(), static_cast<std::streamsize>(buf.size()));
    crc = crc32_update(crc, buf.data(), static_cast<size_t>(in.gcount()));
  }
  return crc;
}

std::string seal_text(uint64_t size, uint32_t crc) {
  return fmt::format("{}size {}\ncrc32 {:08x}\n", kMagic, size, crc);
}

}  // namespace

uint32_t crc32_update(uint32_t crc, const void* data, size_t n) {
  const auto& t = crc_table();
  const auto* p = static_cast<const unsigned char*>(data);
  crc = ~crc;
  for (size_t i = 0; i < n; ++i) crc = t[(crc ^ p[i]) & 0xFF] ^ (crc >> 8);
  return ~crc;
}

void seal_h5_file(const std::string& path, const std::string& what) {
  std::fstream f(path, std::ios::in | std::ios::out | std::ios::binary);
  if (!f) fail("cannot seal {} '{}': the file cannot be opened for writing", what, path);
  std::ifstream in(path, std::ios::binary);
  uint64_t size = 0;
  const uint32_t crc = body_crc(in, size);
  if (size < kH5SealBlock) fail("cannot seal {} '{}': it is shorter than its {}-byte user block", what, path, kH5SealBlock);
  std::string block = seal_text(size, crc);
  block.resize(kH5SealBlock, '\0');
  f.seekp(0);
  f.write(block.data(), static_cast<std::streamsize>(block.size()));
  f.flush();
  if (!f) fail("cannot seal {} '{}': writing its first {} bytes failed (disk full?)", what, path, kH5SealBlock);
}

H5Seal check_h5_seal(const std::string& path, const std::string& what, const std::string& fix) {
  std::ifstream in(path, std::ios::binary);
  if (!in) fail("{} '{}' cannot be read (permission denied?)", what, path);
  std::string head(kH5SealBlock, '\0');
  in.read(head.data(), static_cast<std::streamsize>(head.size()));
  const size_t magic_len = std::strlen(kMagic);
  if (static_cast<size_t>(in.gcount()) < magic_len || head.compare(0, magic_len, kMagic) != 0) {
    // A seal whose first line was damaged still looks like one: refuse it rather
    // than hand libhdf5 a file we know was altered.
    if (in.gcount() >= 12 && head.compare(0, 12, std::string(kMagic, 12)) == 0)
      fail("{} '{}' is damaged: its checksum header (first line '{}') is corrupt; {}", what, path,
           head.substr(0, head.find('\n')), fix);
    return H5Seal::absent;
  }
  in.clear();
  uint64_t size = 0, want_size = 0;
  unsigned want_crc = 0;
  if (std::sscanf(head.c_str() + magic_len, "size %" SCNu64 "\ncrc32 %8x\n", &want_size, &want_crc) != 2)
    fail("{} '{}' is damaged: its checksum header cannot be parsed; {}", what, path, fix);
  const uint32_t crc = body_crc(in, size);
  if (size != want_size)
    fail("{} '{}' is damaged or truncated: it has {} bytes but was written with {}; {}", what, path, size, want_size,
         fix);
  if (crc != want_crc)
    fail("{} '{}' is damaged: its checksum (CRC-32 {:08x}) does not match the one written with it ({:08x}), so "
         "bytes changed after it was written; {} (or, if you edited it in place on purpose, e.g. with h5py, re-seal "
         "it: python3 tools/motionio.py reseal '{}')",
         what, path, crc, want_crc, fix, path);
  return H5Seal::valid;
}

H5Seal guard_h5_read(const std::string& path, const std::string& what, const std::string& fix,
                     const std::function<void()>& probe) {
  const H5Seal seal = check_h5_seal(path, what, fix);
  if (seal == H5Seal::absent) isolated_probe(fmt::format("{} '{}'", what, path), probe, kProbeTimeoutS, fix);
  return seal;
}

}  // namespace mc
