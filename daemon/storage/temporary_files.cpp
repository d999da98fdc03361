#include "slicestation/daemon/storage/temporary_files.hpp"

#include "slicestation/core/atomic_file.hpp"

#include <string>
#include <system_error>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;

bool isTemporaryFileName(std::string_view n) noexcept {
    // `.NAME.tmp.PID.N.STAMP`: core::replaceAtomically, every writer since issue 21.
    if (core::isAtomicTemporaryName(n))
        return true;
    // Older versions' schemes: `.NAME.partial` (the OME-TIFF writer), `NAME.tmp-PID` (results).
    return core::isLegacyTemporaryName(n);
}

core::Result<std::size_t> removeTemporaryFiles(const std::filesystem::path& dir) {
    namespace fs = std::filesystem;
    std::error_code ec;
    if (!fs::exists(dir, ec))
        return std::size_t{0};
    std::size_t removed = 0;
    fs::recursive_directory_iterator it(dir, ec);
    for (; !ec && it != fs::recursive_directory_iterator(); it.increment(ec)) {
        const fs::path p = it->path();
        if (!isTemporaryFileName(p.filename().string()))
            continue;
        std::error_code typeEc;
        if (!it->is_regular_file(typeEc) || it->is_symlink(typeEc))
            continue;
        if (!fs::remove(p, ec) && ec)
            return makeError(ErrorCode::IoError,
                             "cannot remove the temporary file " + p.string() + ": " + ec.message(),
                             ec.value());
        ++removed;
    }
    if (ec)
        return makeError(ErrorCode::IoError,
                         "cannot list " + dir.string() +
                             " to remove temporary files: " + ec.message(),
                         ec.value());
    return removed;
}

} // namespace slicestation::daemon
