// A checksum for the HDF5 files motionctl writes, checked before libhdf5 reads a
// byte of them (issue 16). libhdf5 trusts its metadata: a flipped byte in a global
// heap (variable-length strings) or an object header can crash it inside H5Dread.
// So every HDF5 file motionctl writes (motion and constraint files, flow weights,
// metrics.h5, a row's samples.h5, results.h5) carries a "seal" in HDF5's user
// block, the first 512 bytes, which libhdf5 skips by design: a text header with the
// file's size and the CRC-32 of everything after the block. A file whose seal does
// not match is refused with a UserError before libhdf5 opens it. Files without a
// seal (written before seals, or by other tools) are read as before, under crash
// isolation (core/isolated.h). Layout in docs/formats.md; tools/motionio.py writes
// the same.
#pragma once
#include <cstdint>
#include <functional>
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
// matches; a UserError naming `what`, the file, the defect (size, checksum) and
// `fix` (what to do about it) otherwise.
H5Seal check_h5_seal(const std::string& path, const std::string& what, const std::string& fix = "re-create the file");

// What a reader of a sealed kind of file does before its own read: checks the seal
// (check_h5_seal), and when the file has none runs `probe` (a read of the file whose
// result is discarded) in a forked child (isolated_probe), so a crash inside libhdf5
// on a damaged unsealed file is a UserError naming `what`, the file and `fix`. A
// matching seal needs no probe: the bytes are the ones a motionctl writer produced.
H5Seal guard_h5_read(const std::string& path, const std::string& what, const std::string& fix,
                     const std::function<void()>& probe);

}  // namespace mc
