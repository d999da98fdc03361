#include "slicestation/daemon/storage/temporary_files.hpp"

#include <string>
#include <system_error>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;

namespace {

bool isDigits(std::string_view s) noexcept {
    if (s.empty()) return false;
    for (char c : s)
        if (c < '0' || c > '9') return false;
    return true;
}

/// `rest` is `count` runs of digits separated by '.'.
bool isDottedNumbers(std::string_view rest, int count) noexcept {
    for (int i = 0; i < count; ++i) {
        const std::size_t dot = i + 1 < count ? rest.find('.') : rest.size();
        if (dot == std::string_view::npos || !isDigits(rest.substr(0, dot))) return false;
        rest = dot < rest.size() ? rest.substr(dot + 1) : std::string_view();
    }
    return rest.empty();
}

} // namespace

bool isTemporaryFileName(std::string_view n) noexcept {
    // `.NAME.partial`
    constexpr std::string_view partial = ".partial";
    if (n.size() > partial.size() + 1 && n.front() == '.' && n.ends_with(partial)) return true;
    // `.NAME.tmp.PID.N.STAMP`
    if (n.size() > 1 && n.front() == '.') {
        for (std::size_t at = n.find(".tmp.", 1); at != std::string_view::npos; at = n.find(".tmp.", at + 1))
            if (at > 1 && isDottedNumbers(n.substr(at + 5), 3)) return true;
    }
    // `NAME.tmp-PID`
    const std::size_t dash = n.rfind(".tmp-");
    return dash != std::string_view::npos && dash > 0 && isDigits(n.substr(dash + 5));
}

core::Result<std::size_t> removeTemporaryFiles(const std::filesystem::path& dir) {
    namespace fs = std::filesystem;
    std::error_code ec;
    if (!fs::exists(dir, ec)) return std::size_t{0};
    std::size_t removed = 0;
    fs::recursive_directory_iterator it(dir, ec);
    for (; !ec && it != fs::recursive_directory_iterator(); it.increment(ec)) {
        const fs::path p = it->path();
        if (!isTemporaryFileName(p.filename().string())) continue;
        std::error_code typeEc;
        if (!it->is_regular_file(typeEc) || it->is_symlink(typeEc)) continue;
        if (!fs::remove(p, ec) && ec)
            return makeError(ErrorCode::IoError, "cannot remove the temporary file " + p.string() + ": " +
                                                     ec.message(), ec.value());
        ++removed;
    }
    if (ec)
        return makeError(ErrorCode::IoError, "cannot list " + dir.string() + " to remove temporary files: " +
                                                 ec.message(), ec.value());
    return removed;
}

} // namespace slicestation::daemon
