// The station's views for the outward parts (StationApi's reads): status, records, the export,
// stored images and the atlas region at a pixel.
#include "slicestation/core/image_file.hpp"
#include "slicestation/core/tiff_file.hpp"
#include "slicestation/daemon/export/run_export.hpp"
#include "slicestation/daemon/station/damage_report.hpp"
#include "slicestation/daemon/station/station.hpp"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <sstream>
#include <vector>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;
using core::Result;

namespace {

/// A file the journal refers to, resolved inside the state directory; IoError when it would
/// leave it (a damaged journal must not make the API serve arbitrary files).
Result<std::filesystem::path> storedFile(const std::filesystem::path& stateDir,
                                         const std::string& rel) {
    std::error_code ec;
    const auto root = std::filesystem::weakly_canonical(stateDir, ec);
    if (!ec && !rel.empty()) {
        const auto full = std::filesystem::weakly_canonical(stateDir / rel, ec);
        const auto r = full.lexically_relative(root);
        if (!ec && !r.empty() && *r.begin() != "..")
            return full;
    }
    return makeError(ErrorCode::IoError,
                     "stored path \"" + rel + "\" is outside the state directory");
}

/// The latest capture of a section and its registration, if any. NotFound: no such section, no
/// capture yet, or (`registered`) not registered yet.
Result<std::pair<CaptureRecord, std::optional<RegistrationRecord>>>
latest(Journal& journal, std::int64_t sectionId, bool registered) {
    auto sec = journal.section(sectionId);
    if (!sec)
        return sec.error();
    auto caps = journal.captures(sectionId);
    if (!caps || caps->empty())
        return makeError(ErrorCode::NotFound,
                         "section " + std::to_string(sectionId) + " has no capture yet");
    std::optional<RegistrationRecord> reg;
    if (auto regs = journal.registrations(sectionId))
        for (const auto& r : *regs)
            if (r.captureId == caps->back().id)
                reg = r;
    if (registered && !reg)
        return makeError(ErrorCode::NotFound,
                         "section " + std::to_string(sectionId) + " is not registered yet");
    return std::make_pair(caps->back(), reg);
}

} // namespace

Result<std::vector<RunRecord>> Station::runs() {
    return journal_->runs();
}

Result<RunRecord> Station::run(std::int64_t runId) {
    return journal_->run(runId);
}

Result<std::vector<SectionRecord>> Station::sections(std::int64_t runId) {
    if (auto r = journal_->run(runId); !r)
        return r.error();
    return journal_->sections(runId);
}

Result<std::vector<AlertRecord>> Station::alerts(bool openOnly) {
    // The stored ones first, then those held in memory while the disk is full (not yet
    // acknowledged, so open): in this order an alert stored in between is missed for a moment
    // rather than listed twice.
    auto stored = journal_->alerts(openOnly);
    if (!stored)
        return stored.error();
    for (AlertRecord& held : notifier_->heldAlerts())
        stored->push_back(std::move(held));
    return stored;
}

Result<cv::Mat> Station::sectionImage(std::int64_t sectionId, bool overlay) {
    auto l = latest(*journal_, sectionId, overlay);
    if (!l)
        return l.error();
    auto file = storedFile(parts_.stateDir, overlay ? l->second->overlayPath : l->first.imagePath);
    if (!file)
        return file.error();
    auto img = core::readImage(*file);
    if (!img)
        return makeError(ErrorCode::IoError, img.error().message, img.error().sysErrno);
    return img;
}

namespace {

Result<std::string> readText(const std::filesystem::path& file, const std::string& what) {
    std::error_code ec;
    if (!std::filesystem::exists(file, ec))
        return makeError(ErrorCode::NotFound, what + " has no cell counts (scan.count_cells)");
    std::ifstream in(file, std::ios::binary);
    std::ostringstream text;
    if (!(in && text << in.rdbuf()))
        return makeError(ErrorCode::IoError, what + ": cell counts unreadable");
    return text.str();
}

/// The stored image of a section's latest capture, tiled (Unsupported when it is not).
Result<std::pair<std::filesystem::path, core::TiffPyramidInfo>>
tiledImage(Journal& journal, const std::filesystem::path& stateDir, std::int64_t sectionId) {
    auto l = latest(journal, sectionId, false);
    if (!l)
        return l.error();
    auto file = storedFile(stateDir, l->first.imagePath);
    if (!file)
        return file.error();
    auto info = core::readTiffPyramidInfo(*file);
    if (!info)
        return makeError(info.error().code == ErrorCode::NotFound ? ErrorCode::IoError
                                                                  : info.error().code,
                         info.error().message);
    if (!info->tiled || info->tileSize.width <= 0 || info->tileSize.width > 4096)
        return makeError(ErrorCode::Unsupported, "the image of section " +
                                                     std::to_string(sectionId) +
                                                     " is not tiled (written before pyramids)");
    return std::make_pair(*file, *info);
}

/// 16-bit to 8-bit by the 0.5 and 99.5 percentiles of the smallest level (one mapping for
/// every tile of an image, so that tiles side by side match).
Result<cv::Mat> stretchTile(const std::filesystem::path& file, const core::TiffPyramidInfo& info,
                            const cv::Mat& tile) {
    const int top = static_cast<int>(info.levels.size()) - 1;
    const cv::Size size = info.levels.back();
    const int t = info.tileSize.width;
    std::vector<std::uint16_t> samples;
    for (int ty = 0; ty * t < size.height; ++ty)
        for (int tx = 0; tx * t < size.width; ++tx) {
            auto part = core::readTiffTile(file, top, tx, ty);
            if (!part)
                return part.error();
            for (int y = 0; y < part->rows; ++y)
                for (int x = 0; x < part->cols; x += 3)
                    samples.push_back(part->at<std::uint16_t>(y, x));
        }
    if (samples.empty())
        return makeError(ErrorCode::IoError, "empty top level");
    const auto at = [&](double q) {
        auto k = samples.begin() + static_cast<std::ptrdiff_t>(q * (samples.size() - 1));
        std::nth_element(samples.begin(), k, samples.end());
        return static_cast<double>(*k);
    };
    const double lo = at(0.005);
    const double hi = std::max(at(0.995), lo + 1);
    cv::Mat out;
    tile.convertTo(out, CV_8U, 255.0 / (hi - lo), -lo * 255.0 / (hi - lo));
    return out;
}

} // namespace

Result<std::string> Station::sectionCounts(std::int64_t sectionId) {
    auto l = latest(*journal_, sectionId, true);
    if (!l)
        return l.error();
    // Written beside the result by the registration worker: <base>.result.json ->
    // <base>.counts.csv.
    std::string rel = l->second->resultPath;
    const std::string suffix = ".result.json";
    if (rel.size() <= suffix.size() ||
        rel.compare(rel.size() - suffix.size(), suffix.size(), suffix) != 0)
        return makeError(ErrorCode::NotFound,
                         "section " + std::to_string(sectionId) + " has no cell counts");
    rel = rel.substr(0, rel.size() - suffix.size()) + ".counts.csv";
    auto file = storedFile(parts_.stateDir, rel);
    if (!file)
        return file.error();
    return readText(*file, "section " + std::to_string(sectionId));
}

Result<std::string> Station::runCounts(std::int64_t runId) {
    if (auto r = journal_->run(runId); !r)
        return r.error();
    return readText(parts_.stateDir / "runs" / std::to_string(runId) / "run-counts.csv",
                    "run " + std::to_string(runId));
}

Result<ImagePyramid> Station::sectionPyramid(std::int64_t sectionId) {
    auto image = tiledImage(*journal_, parts_.stateDir, sectionId);
    if (!image)
        return image.error();
    return ImagePyramid{image->second.tileSize.width, image->second.levels};
}

Result<cv::Mat> Station::sectionTile(std::int64_t sectionId, int level, int x, int y) {
    auto image = tiledImage(*journal_, parts_.stateDir, sectionId);
    if (!image)
        return image.error();
    const auto& [file, info] = *image;
    auto tile = core::readTiffTile(file, level, x, y);
    if (!tile)
        return tile.error();
    if (tile->depth() == CV_8U)
        return tile;
    if (tile->channels() != 1)
        return makeError(ErrorCode::Unsupported, "16-bit colour tiles are not shown");
    return stretchTile(file, info, *tile);
}

Result<RegionAtPixel> Station::regionAt(std::int64_t sectionId, int x, int y, int ofWidth) {
    auto l = latest(*journal_, sectionId, true);
    if (!l)
        return l.error();
    auto file = storedFile(parts_.stateDir, l->second->labelsPath);
    if (!file)
        return makeError(ErrorCode::IoError, "stored labels path is outside the state directory");
    RegionAtPixel out;
    {
        std::lock_guard lock(labelsMutex_);
        if (labelsPath_ != file->string()) {
            auto img = core::readImage(*file);
            if (!img || img->type() != CV_32SC1)
                return makeError(ErrorCode::IoError, "labels unreadable");
            labels_ = *img;
            labelsPath_ = file->string();
        }
        // In double, and checked before the cast: scaled, x and y may lie far beyond int.
        double fx = x, fy = y;
        if (ofWidth > 0) {
            const double f = static_cast<double>(labels_.cols) / ofWidth;
            fx = std::floor((fx + 0.5) * f);
            fy = std::floor((fy + 0.5) * f);
        }
        if (!(fx >= 0 && fx < labels_.cols && fy >= 0 && fy < labels_.rows))
            return makeError(ErrorCode::InvalidArgument,
                             "x, y: outside the " + std::to_string(labels_.cols) + "x" +
                                 std::to_string(labels_.rows) + " image");
        out.x = static_cast<int>(fx);
        out.y = static_cast<int>(fy);
        out.id = labels_.at<std::int32_t>(out.y, out.x);
    }
    if (out.id > 0)
        if (const StackRegion* r = findRegion(stack_, static_cast<std::uint32_t>(out.id))) {
            out.name = r->name;
            out.acronym = r->acronym;
        }
    return out;
}

nlohmann::json Station::status() {
    nlohmann::json j;
    const auto active = scanner_->activeRun();
    j["state"] = active ? "scanning" : (scanner_->idle() ? "idle" : "working");
    j["activity"] = scanner_->activity();
    j["active_run"] = active ? nlohmann::json(*active) : nlohmann::json();
    j["simulated"] = {{"stage", parts_.simulatedStage}, {"camera", parts_.simulatedCamera}};
    j["atlas"] = {{"dir", stack_.dir.string()}, {"slices", stack_.slices.size()}};
    j["state_dir"] = parts_.stateDir.string();
    if (auto a = journal_->alerts(true))
        j["open_alerts"] = a->size();
    if (auto f = parts_.freeSpace(parts_.stateDir))
        j["free_mb"] = static_cast<double>(*f) / (1 << 20);
    {
        std::lock_guard lock(stageMutex_);
        if (stage_)
            j["stage"] = {{"x_um", stage_->xUm},
                          {"y_um", stage_->yUm},
                          {"z_um", stage_->zUm},
                          {"moving", stageMoving_}};
    }
    j["phases"] = stats_.summary();
    if (active)
        if (auto r = journal_->run(*active))
            j["run"] = toJson(*r);
    return j;
}

Result<nlohmann::json> Station::sectionDetail(std::int64_t sectionId) {
    auto s = journal_->section(sectionId);
    if (!s)
        return s.error();
    nlohmann::json j = toJson(*s);
    auto caps = journal_->captures(sectionId);
    if (!caps)
        return caps.error();
    auto regs = journal_->registrations(sectionId);
    if (!regs)
        return regs.error();
    j["captures"] = nlohmann::json::array();
    for (const auto& c : *caps)
        j["captures"].push_back(toJson(c));
    j["registrations"] = nlohmann::json::array();
    for (const auto& r : *regs) {
        nlohmann::json rj = toJson(r);
        if (r.result.contains("damage_regions"))
            rj["damage_regions"] = r.result["damage_regions"];
        if (r.result.contains("regions"))
            rj["regions"] = r.result["regions"];
        if (r.result.contains("quality"))
            rj["quality_detail"] = r.result["quality"];
        j["registrations"].push_back(rj);
    }
    // The section's planes (planned, own match, found, series) as its latest registration has them.
    j["plane"] = regs->empty() ? nlohmann::json() : planeJson(regs->back());
    return j;
}

namespace {
std::string csvField(const std::string& s) {
    if (s.find_first_of(",\"\n") == std::string::npos)
        return s;
    std::string out = "\"";
    for (char c : s)
        out += c == '"' ? std::string("\"\"") : std::string(1, c);
    return out + "\"";
}
} // namespace

Result<std::string> Station::exportRun(std::int64_t runId, const std::string& format) {
    if (isResultExportFormat(format)) // QuickNII/VisuAlign, QuPath: docs/results.md
        return exportRunResults(*journal_, stateDir(), runId, format);
    if (format != "json" && format != "csv")
        return makeError(ErrorCode::InvalidArgument,
                         "format: expected json, csv, quicknii or qupath, got \"" + format + "\"");
    auto run = journal_->run(runId);
    if (!run)
        return run.error();
    auto secs = journal_->sections(runId);
    if (!secs)
        return secs.error();
    nlohmann::json rows = nlohmann::json::array();
    for (const auto& s : *secs) {
        nlohmann::json row{
            {"run_id", runId},    {"slide", s.slideName},       {"section", s.name},
            {"section_id", s.id}, {"state", toString(s.state)}, {"attempts", s.attempts}};
        row["expected_slice"] =
            s.expectedSlice ? nlohmann::json(*s.expectedSlice) : nlohmann::json();
        auto caps = journal_->captures(s.id);
        auto regs = journal_->registrations(s.id);
        if (caps && !caps->empty()) {
            const auto& c = caps->back();
            row["image"] = c.imagePath;
            row["stage_x_um"] = c.stage.xUm;
            row["stage_y_um"] = c.stage.yUm;
            row["stage_z_um"] = c.stage.zUm;
            row["um_per_px"] = c.umPerPx;
            row["focus_found"] = c.focusFound;
            if (regs)
                for (const auto& r : *regs)
                    if (r.captureId == c.id) {
                        row["atlas_slice"] = r.atlasSlice;
                        row["matched_slice"] =
                            r.matchedSlice ? nlohmann::json(*r.matchedSlice) : nlohmann::json();
                        row["quality"] = r.quality;
                        row["damaged"] = r.damaged;
                        row["damage_fraction"] = r.damageFraction;
                        row["damage_summary"] = r.summary;
                        row["warning"] = r.warning;
                        row["overlay"] = r.overlayPath;
                    }
        }
        rows.push_back(row);
    }
    if (format == "json")
        return nlohmann::json{{"run", toJson(*run)}, {"sections", rows}}.dump(2) + "\n";
    static const char* cols[] = {
        "run_id",    "slide",       "section",         "section_id",     "state",
        "attempts",  "image",       "stage_x_um",      "stage_y_um",     "stage_z_um",
        "um_per_px", "focus_found", "expected_slice",  "atlas_slice",    "matched_slice",
        "quality",   "damaged",     "damage_fraction", "damage_summary", "warning",
        "overlay"};
    std::ostringstream os;
    for (std::size_t i = 0; i < std::size(cols); ++i)
        os << (i ? "," : "") << cols[i];
    os << "\n";
    for (const auto& row : rows) {
        for (std::size_t i = 0; i < std::size(cols); ++i) {
            if (i)
                os << ",";
            if (!row.contains(cols[i]) || row[cols[i]].is_null())
                continue;
            const auto& v = row[cols[i]];
            os << csvField(v.is_string() ? v.get<std::string>() : v.dump());
        }
        os << "\n";
    }
    return os.str();
}

namespace {
constexpr const char* kFlagScoreKey = "damage.flag_score";
} // namespace

Result<ScanSettings> Station::settingsForNewRun() {
    ScanSettings scan = parts_.settings.scan;
    auto set = journal_->setting(kFlagScoreKey);
    if (!set)
        return set.error();
    if (*set) {
        const auto& v = (*set)->value;
        if (!v.is_number() || !(v.get<double>() >= 0 && v.get<double>() <= 1))
            return makeError(ErrorCode::IoError, std::string("journal setting ") + kFlagScoreKey +
                                                     ": expected a number in [0, 1], got " +
                                                     v.dump());
        scan.damageFlagScore = v.get<double>();
    }
    return scan;
}

Result<nlohmann::json> Station::damageThreshold() {
    auto set = journal_->setting(kFlagScoreKey);
    if (!set)
        return set.error();
    auto scan = settingsForNewRun();
    if (!scan)
        return scan.error();
    nlohmann::json j{{"flag_score", scan->damageFlagScore},
                     {"station_file_flag_score", parts_.settings.scan.damageFlagScore},
                     {"source", *set ? "set" : "station file"}};
    j["set_utc"] = *set ? nlohmann::json((*set)->setUtc) : nlohmann::json();
    return j;
}

Result<nlohmann::json> Station::setDamageThreshold(std::optional<double> flagScore) {
    if (flagScore && !(*flagScore >= 0 && *flagScore <= 1))
        return makeError(ErrorCode::OutOfRange, "flag_score: expected a number in [0, 1]");
    auto r = flagScore ? journal_->setSetting(kFlagScoreKey, *flagScore)
                       : journal_->clearSetting(kFlagScoreKey);
    if (!r)
        return r.error();
    auto j = damageThreshold();
    if (j)
        notifier_->publish({"damage_threshold", *j});
    return j;
}

Result<nlohmann::json> Station::damageReport(const std::string& sinceUtc,
                                             double targetFalseAlarmRate) {
    auto since = parseSinceUtc(sinceUtc);
    if (!since)
        return since.error();
    auto flags = journal_->damageFlags(*since);
    if (!flags)
        return flags.error();
    auto report = computeDamageReport(*flags, targetFalseAlarmRate);
    if (!report)
        return report.error();
    auto threshold = damageThreshold();
    if (!threshold)
        return threshold.error();
    nlohmann::json j = toJson(*report);
    j["since"] = *since;
    j["current"] = *threshold;
    return j;
}

std::shared_ptr<const hw::Frame> Station::liveFrame() const {
    std::lock_guard lock(liveMutex_);
    return live_;
}

} // namespace slicestation::daemon
