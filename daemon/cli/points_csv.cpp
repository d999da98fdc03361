#include "slicestation/daemon/cli/points_csv.hpp"

#include "slicestation/core/csv.hpp"

#include <algorithm>
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
    auto records = core::parseCsv(text, "points CSV");
    if (!records)
        return records.error();
    std::vector<cv::Point2d> points;
    bool header = false;
    for (const core::CsvRecord& record : *records) {
        std::vector<std::string_view> fields;
        for (const std::string& f : record.fields)
            fields.push_back(trim(f)); // spaces around numbers are allowed
        if (std::all_of(fields.begin(), fields.end(), [](auto f) { return f.empty(); }))
            continue; // a line of spaces
        const std::string where = "points CSV line " + std::to_string(record.line) + ": ";
        if (!header) {
            if (fields.size() < 2 || fields[0] != "x" || fields[1] != "y") {
                std::string got;
                for (const auto& f : record.fields)
                    got += (got.empty() ? "" : ",") + f;
                return makeError(ErrorCode::InvalidArgument,
                                 where + "expected the header \"x,y\", got \"" + got + "\"");
            }
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
