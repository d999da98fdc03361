#pragma once
/// The temporary files of the station's atomic writers, and their removal after a crash.
///
/// Every file is written through core::replaceAtomically (atomic_file.hpp): a temporary file
/// `.NAME.tmp.PID.N.STAMP` beside its target, fsync'ed and renamed into place, so a kill leaves
/// at most a temporary file, which nothing refers to. Older versions named them two other ways,
/// and a state directory may still hold those; isTemporaryFileName() knows all three:
///   `.NAME.tmp.PID.N.STAMP`    every writer now
///   `.NAME.partial`            the OME-TIFF writer before issue 21
///   `NAME.tmp-PID`             the result/manifest writer before issue 21
/// (PID, N and STAMP are decimal numbers.)
///
/// Threading: plain functions; removeTemporaryFiles() must run while no writer is writing into
/// the directory (the station calls it at start, before the scan loop and the worker start).
#include "slicestation/core/result.hpp"

#include <cstddef>
#include <filesystem>
#include <string_view>

namespace slicestation::daemon {

/// True when `fileName` (a name, not a path) is one of the temporary names above.
bool isTemporaryFileName(std::string_view fileName) noexcept;

/// Removes every regular file below `dir` (recursively, symbolic links not followed) whose name
/// isTemporaryFileName(). A missing `dir` is not an error.
/// \return how many were removed; IoError naming the path when one cannot be listed or removed.
[[nodiscard]] core::Result<std::size_t> removeTemporaryFiles(const std::filesystem::path& dir);

} // namespace slicestation::daemon
