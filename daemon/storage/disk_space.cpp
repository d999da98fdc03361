#include "slicestation/daemon/storage/disk_space.hpp"

#include <sys/statvfs.h>

#include <cerrno>
#include <cstring>
#include <string>

namespace slicestation::daemon {

core::Result<std::uint64_t> availableBytes(const std::filesystem::path& dir) {
    struct statvfs st {};
    if (::statvfs(dir.c_str(), &st) != 0) {
        const int err = errno;
        const auto code =
            err == ENOENT || err == ENOTDIR ? core::ErrorCode::NotFound : core::ErrorCode::IoError;
        return core::makeError(code,
                               "cannot read the free space of '" + dir.string() + "': " +
                                   std::strerror(err) + " (errno " + std::to_string(err) + ")",
                               err);
    }
    // f_frsize is the unit of the block counts (f_bsize may differ on some file systems).
    const std::uint64_t unit = st.f_frsize != 0 ? st.f_frsize : st.f_bsize;
    return static_cast<std::uint64_t>(st.f_bavail) * unit;
}

} // namespace slicestation::daemon
