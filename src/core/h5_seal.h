// A checksum for the HDF5 files motionctl writes, checked before libhdf5 reads a
// byte of them (issue 16). libhdf5 trusts its metadata: a flipped byte in a global
// heap (variable-length strings) or an object header can crash it inside H5Dread.
// So every motion file carries a "seal" in HDF5's user block, the first 512
// bytes, which libhdf5 skips by design: a text header with the file's size and the
// CRC-32 of everything after the block. A file whose seal does not match is
// refused with a UserError before libhdf5 opens it. Files without a seal (written
// before seals, or by other tools) are read as before, under crash isolation
// (core/isolated.h). Layout in docs/formats.md; tools/motionio.py writes the same.
#pragma once
#include <cstdint>
#include <string>

namespace mc {

inline constexpr unsigned kH5SealBlock = 512;  // HDF5 user block size (a power of two >= 512)

// CRC-32 (IEEE 802.3, as zlib.crc32) of `n` bytes, continuing from `crc`.
uint32_t crc32_update(uint32_t crc, const void* data, size_t n);

// Writes the seal into the user block of a closed HDF5 file created with a user
// block of kH5SealBlock bytes (H5Pset_userblock). UserError naming `what` on I/O errors.
void seal_h5_file(const std::string& path, const std::string& what);

enum class H5Seal { absent, valid };

// `absent` when the file has no seal (an older or foreign file), `valid` when it
// matches; a UserError naming `what` and the defect (size, checksum) otherwise.
H5Seal check_h5_seal(const std::string& path, const std::string& what);

}  // namespace mc
