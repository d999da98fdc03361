#include "slicestation/daemon/cli/points_csv.hpp"

#include <cerrno>
#include <charconv>
#include <cmath>
#include <fstream>
#include <sstream>
#include <string>

namespace slicestation::daemon {
namespace {

using core::ErrorCode;
using core::makeError;

std::string_view trim(std::string_view s) {
    while (!s.empty() && (s.front() == ' ' || s.front() == '\t'))
        s.remove_prefix(1);
    while (!s.empty() && (s.back() == ' ' || s.back() == '\t' || s.back() == '\r'))
        s.remove_suffix(1);
    return s;
}

std::vector<std::string_view> split(std::string_view line) {
    std::vector<std::string_view> out;
    size_t start = 0;
    for (;;) {
        const size_t comma = line.find(',', start);
        out.push_back(trim(line.substr(start, comma - start)));
        if (comma == std::string_view::npos)
            break;
        start = comma + 1;
    }
    return out;
}

bool parseNumber(std::string_view s, double& out) {
    if (s.empty())
        return false;
    // strtod accepts what CSV writers produce (1e3, -0.5, +2); require the whole field to parse.
    const std::string copy(s);
    char* end = nullptr;
    errno = 0;
    out = std::strtod(copy.c_str(), &end);
    return end == copy.c_str() + copy.size() && errno == 0 && std::isfinite(out);
}

} // namespace

core::Result<std::vector<cv::Point2d>> parsePointsCsv(std::string_view text) {
    std::vector<cv::Point2d> points;
    bool header = false;
    size_t lineNo = 0, pos = 0;
    if (text.substr(0, 3) == "\xEF\xBB\xBF")
        pos = 3; // UTF-8 byte-order mark from spreadsheets
    while (pos <= text.size()) {
        const size_t nl = text.find('\n', pos);
        const std::string_view line =
            trim(text.substr(pos, nl == std::string_view::npos ? text.size() - pos : nl - pos));
        ++lineNo;
        pos = nl == std::string_view::npos ? text.size() + 1 : nl + 1;
        if (line.empty())
            continue;
        const auto fields = split(line);
        const std::string where = "points CSV line " + std::to_string(lineNo) + ": ";
        if (!header) {
            if (fields.size() < 2 || fields[0] != "x" || fields[1] != "y")
                return makeError(ErrorCode::InvalidArgument,
                                 where + "expected the header \"x,y\", got \"" + std::string(line) +
                                     "\"");
            header = true;
            continue;
        }
        if (fields.size() < 2)
            return makeError(ErrorCode::InvalidArgument,
                             where + "expected 2 fields, got " + std::to_string(fields.size()));
        double x = 0, y = 0;
        if (!parseNumber(fields[0], x))
            return makeError(ErrorCode::InvalidArgument,
                             where + "x is not a number: \"" + std::string(fields[0]) + "\"");
        if (!parseNumber(fields[1], y))
            return makeError(ErrorCode::InvalidArgument,
                             where + "y is not a number: \"" + std::string(fields[1]) + "\"");
        points.emplace_back(x, y);
    }
    if (!header)
        return makeError(ErrorCode::InvalidArgument, "points CSV is empty (no x,y header)");
    return points;
}

core::Result<std::vector<cv::Point2d>> readPointsCsv(const std::filesystem::path& path) {
    std::error_code ec;
    if (!std::filesystem::exists(path, ec))
        return makeError(ErrorCode::NotFound, "points file not found: " + path.string());
    std::ifstream in(path, std::ios::binary);
    if (!in)
        return makeError(ErrorCode::IoError, "cannot read points file " + path.string(), errno);
    std::ostringstream ss;
    ss << in.rdbuf();
    auto r = parsePointsCsv(ss.str());
    if (!r)
        return makeError(r.error().code, path.string() + ": " + r.error().message);
    return r;
}

} // namespace slicestation::daemon
