#pragma once
/// Files replaced atomically: the one writer every file of the station goes through (images,
/// label images, OME-TIFF sections, result documents, manifests). The data goes to a temporary
/// file beside the target, named `.NAME.tmp.PID.N.STAMP` (PID, N and STAMP decimal numbers), which
/// is fsync'ed, renamed to the target, and the directory fsync'ed: a reader never sees half a
/// file, and a crash leaves at most the temporary file, which nothing refers to
/// (isAtomicTemporaryName() tells them, for the clean-up after a crash).
///
/// Threading: re-entrant; different targets may be written concurrently (the temporary names
/// differ by process, counter and time). Blocking: file I/O and fsync, no timeout.
#include "slicestation/core/result.hpp"

#include <filesystem>
#include <functional>
#include <string_view>

namespace slicestation::core {

enum class Replace {
    Allowed, ///< an existing target is replaced (rename)
    Never    ///< an existing target stays: IoError with sysErrno EEXIST (renameat2
             ///< RENAME_NOREPLACE, or link + unlink where the file system lacks it)
};

/// Writes the temporary file through `fd` (or by path, e.g. libtiff opening it itself).
using FillTemporary = std::function<Result<void>(int fd, const std::filesystem::path& temporary)>;

/// Creates the temporary file (0666 minus the umask), lets `fill` write it, then fsync, rename
/// and directory fsync (a directory that cannot be fsync'ed, EINVAL, is not an error). On any
/// failure the temporary file is removed and the target is untouched.
/// \return fill's error; NotFound (the directory does not exist), IoError with sysErrno naming
///         the path (ENOSPC, EEXIST under Replace::Never, EACCES, ...).
[[nodiscard]] Result<void> replaceAtomically(const std::filesystem::path& path,
                                             const FillTemporary& fill,
                                             Replace mode = Replace::Allowed);

/// replaceAtomically with `bytes` as the content.
[[nodiscard]] Result<void> writeFileAtomically(const std::filesystem::path& path,
                                               std::string_view bytes,
                                               Replace mode = Replace::Allowed);

/// True when `fileName` (a name, not a path) is a temporary name of this writer.
bool isAtomicTemporaryName(std::string_view fileName) noexcept;

/// True when `fileName` is a temporary name of the writers this one replaced (slicestation
/// before issue 21): `.NAME.partial` (the OME-TIFF writer) and `NAME.tmp-PID` (results). A state
/// directory may still hold them after a crash; its cleanup removes them with the current ones.
bool isLegacyTemporaryName(std::string_view fileName) noexcept;

} // namespace slicestation::core
