#pragma once
/// The temporary files of the station's atomic writers, and their removal after a crash.
///
/// Every writer writes a temporary file beside its target, fsyncs it and renames it into place,
/// so a kill leaves at most a temporary file, which nothing refers to. The three writers name
/// them differently; isTemporaryFileName() knows every scheme:
///   `.NAME.partial`            writeOmeTiffAtomic (section images)
///   `.NAME.tmp.PID.N.STAMP`    core::writeImage and the other core image writers (overlays,
///                              label images, atlas slices)
///   `NAME.tmp-PID`             writeFileAtomically (registration results, manifests)
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
