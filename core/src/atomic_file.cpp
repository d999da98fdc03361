#include "slicestation/core/atomic_file.hpp"

#include "slicestation/core/unique_fd.hpp"

#include <fcntl.h>
#include <stdio.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <string>

namespace slicestation::core {

namespace fs = std::filesystem;

namespace {

std::string quoted(const fs::path& p) {
    return "\"" + p.string() + "\"";
}

/// Digits only, at least one.
bool isNumber(std::string_view s) noexcept {
    if (s.empty())
        return false;
    for (char c : s)
        if (c < '0' || c > '9')
            return false;
    return true;
}

Result<void> writeAll(int fd, std::string_view bytes, const fs::path& path) {
    std::size_t done = 0;
    while (done < bytes.size()) {
        const ssize_t n = ::write(fd, bytes.data() + done, bytes.size() - done);
        if (n < 0 && errno == EINTR)
            continue;
        if (n <= 0) {
            const int err = errno;
            return makeError(ErrorCode::IoError,
                             "cannot write " + quoted(path) + ": " + std::strerror(err), err);
        }
        done += static_cast<std::size_t>(n);
    }
    return {};
}

/// A new temporary file beside `path`; `fd` invalid on failure (errno set).
UniqueFd createTemporary(const fs::path& dir, const fs::path& path, fs::path& tmp) {
    static std::atomic<unsigned> counter{0};
    for (int attempt = 0; attempt < 100; ++attempt) {
        const auto stamp = std::chrono::steady_clock::now().time_since_epoch().count();
        tmp = dir / ("." + path.filename().string() + ".tmp." + std::to_string(::getpid()) + "." +
                     std::to_string(counter.fetch_add(1)) + "." + std::to_string(stamp % 100000));
        UniqueFd fd(::open(tmp.c_str(), O_RDWR | O_CREAT | O_EXCL | O_CLOEXEC, 0666));
        if (fd || errno != EEXIST)
            return fd;
    }
    return UniqueFd();
}

/// Renames without replacing: renameat2 RENAME_NOREPLACE, else link + unlink.
int renameNoReplace(const fs::path& from, const fs::path& to) {
    int r = ::renameat2(AT_FDCWD, from.c_str(), AT_FDCWD, to.c_str(), RENAME_NOREPLACE);
    if (r != 0 && (errno == EINVAL || errno == ENOSYS)) {
        r = ::link(from.c_str(), to.c_str());
        if (r == 0)
            ::unlink(from.c_str());
    }
    return r;
}

} // namespace

Result<void> replaceAtomically(const fs::path& path, const FillTemporary& fill, Replace mode) {
    const fs::path dir = path.parent_path().empty() ? fs::path(".") : path.parent_path();
    fs::path tmp;
    UniqueFd fd = createTemporary(dir, path, tmp);
    if (!fd) {
        const int err = errno;
        const ErrorCode code =
            err == ENOENT || err == ENOTDIR ? ErrorCode::NotFound : ErrorCode::IoError;
        return makeError(code,
                         "cannot create a file in directory " + quoted(dir) + " to write " +
                             quoted(path) + ": " + std::strerror(err),
                         err);
    }
    bool committed = false;
    struct Remover {
        const fs::path& file;
        const bool& keep;
        ~Remover() {
            if (!keep)
                ::unlink(file.c_str());
        }
    } remover{tmp, committed};

    if (auto filled = fill(fd.get(), tmp); !filled)
        return filled.error();
    // fsync flushes the file's data whichever descriptor wrote it (libtiff may use its own).
    if (::fsync(fd.get()) != 0 || ::close(fd.release()) != 0) {
        const int err = errno;
        return makeError(ErrorCode::IoError,
                         "cannot flush " + quoted(tmp) + " to disk: " + std::strerror(err), err);
    }
    const int renamed =
        mode == Replace::Never ? renameNoReplace(tmp, path) : ::rename(tmp.c_str(), path.c_str());
    if (renamed != 0) {
        const int err = errno;
        return makeError(ErrorCode::IoError,
                         err == EEXIST ? quoted(path) + " exists already; it is never replaced"
                                       : "cannot rename " + quoted(tmp) + " to " + quoted(path) +
                                             ": " + std::strerror(err),
                         err);
    }
    committed = true;
    // Make the rename itself durable. Some file systems cannot fsync a directory (EINVAL).
    UniqueFd dirFd(::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC));
    if (!dirFd || (::fsync(dirFd.get()) != 0 && errno != EINVAL)) {
        const int err = errno;
        return makeError(ErrorCode::IoError,
                         "cannot fsync directory " + quoted(dir) + " after writing " +
                             quoted(path) + ": " + std::strerror(err),
                         err);
    }
    return {};
}

Result<void> writeFileAtomically(const fs::path& path, std::string_view bytes, Replace mode) {
    return replaceAtomically(
        path, [&](int fd, const fs::path&) { return writeAll(fd, bytes, path); }, mode);
}

bool isAtomicTemporaryName(std::string_view name) noexcept {
    // .NAME.tmp.PID.N.STAMP
    if (name.size() < 2 || name[0] != '.')
        return false;
    std::string_view rest = name;
    for (int i = 0; i < 3; ++i) { // STAMP, N, PID from the end
        const auto dot = rest.rfind('.');
        if (dot == std::string_view::npos || !isNumber(rest.substr(dot + 1)))
            return false;
        rest = rest.substr(0, dot);
    }
    return rest.size() > 5 && rest.substr(rest.size() - 4) == ".tmp";
}

bool isLegacyTemporaryName(std::string_view name) noexcept {
    constexpr std::string_view partial = ".partial"; // .NAME.partial
    if (name.size() > partial.size() + 1 && name.front() == '.' && name.ends_with(partial))
        return true;
    const std::size_t dash = name.rfind(".tmp-"); // NAME.tmp-PID
    return dash != std::string_view::npos && dash > 0 && isNumber(name.substr(dash + 5));
}

} // namespace slicestation::core
