#pragma once
/// Free space on the file system that holds a directory, checked before every image write.

#include "slicestation/core/result.hpp"

#include <cstdint>
#include <filesystem>

namespace slicestation::daemon {

/// Bytes an unprivileged process may still write on the file system holding `dir`
/// (statvfs: f_bavail * f_frsize; the root-reserved blocks are not counted).
/// Blocking: one statvfs call (may stall on a hung network file system); re-entrant.
/// \return NotFound (`dir` or a parent does not exist), IoError with Error::sysErrno for any
///         other statvfs failure (EACCES, ELOOP, EIO, ...).
[[nodiscard]] core::Result<std::uint64_t> availableBytes(const std::filesystem::path& dir);

} // namespace slicestation::daemon
