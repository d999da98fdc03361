#include "slicestation/daemon/station/station.hpp"

#include "slicestation/daemon/storage/disk_space.hpp"
#include "slicestation/daemon/config/scan_plan.hpp"
#include "slicestation/daemon/storage/temporary_files.hpp"

#include <iostream>
#include <sstream>

namespace slicestation::daemon {

namespace {

/// Reports every position the stage settled at (moves made by autofocus too), so a simulated
/// camera renders what lies under the objective. Forwards everything else unchanged.
class ReportingStage final : public hw::Stage {
public:
    ReportingStage(std::unique_ptr<hw::Stage> inner, std::function<void(const hw::StagePosition&)> report)
        : inner_(std::move(inner)), report_(std::move(report)) {}
    hw::StageLimits limits() const override { return inner_->limits(); }
    core::Result<hw::StagePosition> position(std::chrono::milliseconds t) override { return inner_->position(t); }
    core::Result<hw::StagePosition> moveTo(const hw::StagePosition& p, std::chrono::milliseconds t) override {
        return reported(inner_->moveTo(p, t));
    }
    core::Result<hw::StagePosition> home(std::chrono::milliseconds t) override { return reported(inner_->home(t)); }
    void stop() noexcept override { inner_->stop(); }
    core::Result<hw::StageAlarm> alarm(std::chrono::milliseconds t) override { return inner_->alarm(t); }
    core::Result<void> resetAlarm(std::chrono::milliseconds t) override { return inner_->resetAlarm(t); }

private:
    core::Result<hw::StagePosition> reported(core::Result<hw::StagePosition> r) {
        if (r) report_(*r);
        return r;
    }
    std::unique_ptr<hw::Stage> inner_;
    std::function<void(const hw::StagePosition&)> report_;
};

/// Hands every frame the camera delivers (autofocus frames too) to the live view.
class LiveCamera final : public hw::Camera {
public:
    LiveCamera(std::unique_ptr<hw::Camera> inner, std::function<void(const hw::Frame&)> seen)
        : inner_(std::move(inner)), seen_(std::move(seen)) {}
    core::Result<hw::CameraSettings> configure(const hw::CameraSettings& s, std::chrono::milliseconds t) override {
        return inner_->configure(s, t);
    }
    core::Result<hw::Frame> capture(std::chrono::milliseconds t) override {
        auto f = inner_->capture(t);
        if (f) seen_(*f);
        return f;
    }
    void stop() noexcept override { inner_->stop(); }

private:
    std::unique_ptr<hw::Camera> inner_;
    std::function<void(const hw::Frame&)> seen_;
};

} // namespace

using core::ErrorCode;
using core::makeError;
using core::Result;

Result<AtlasStack> openAtlasStack(const DaemonSettings& settings, const std::filesystem::path& stateDir) {
    if (settings.atlas != "builtin") {
        auto s = readStack(settings.atlas);
        if (!s) return makeError(s.error().code, "daemon.atlas: " + s.error().message);
        return s;
    }
    std::ostringstream name;
    name << "atlas-builtin-" << static_cast<int>(settings.builtinIntervalUm) << "um";
    const auto dir = stateDir / name.str();
    if (std::filesystem::exists(dir / "manifest.json")) {
        auto s = readStack(dir);
        if (s) return s;
        // A damaged copy of the built-in stack is rebuilt: it holds nothing of the user's.
        std::cerr << "<4>built-in atlas at " << dir << " unreadable (" << s.error().message
                  << "); writing it again" << std::endl;
    }
    auto slices = builtinStackSlices(settings.builtinIntervalUm, 0);
    if (!slices) return slices.error();
    return writeStack(dir, *slices, builtinStackRegions(),
                      {{"kind", "builtin"}, {"plane", "coronal"}, {"interval_um", settings.builtinIntervalUm}});
}

Result<std::unique_ptr<Station>> Station::create(StationParts parts) {
    if (!parts.stage || !parts.camera)
        return makeError(ErrorCode::InvalidArgument, "station: a stage and a camera are required");
    std::error_code ec;
    std::filesystem::create_directories(parts.stateDir, ec);
    if (ec)
        return makeError(ErrorCode::IoError, "state directory " + parts.stateDir.string() + ": " + ec.message(),
                         ec.value());
    if (parts.stageMoved) {
        parts.stage = std::make_unique<ReportingStage>(std::move(parts.stage), parts.stageMoved);
        parts.stageMoved = nullptr;
    }
    if (!parts.freeSpace) parts.freeSpace = [](const std::filesystem::path& p) { return availableBytes(p); };
    std::unique_ptr<Station> st(new Station(std::move(parts)));
    {
        Station* self = st.get();
        st->parts_.camera = std::make_unique<LiveCamera>(std::move(st->parts_.camera), [self](const hw::Frame& f) {
            auto copy = std::make_shared<const hw::Frame>(f); // ~2.6 MB for 1280x1024x16 bit
            std::lock_guard lock(self->liveMutex_);
            self->live_ = std::move(copy);
        });
    }
    auto journal = Journal::open(st->parts_.stateDir / "journal.sqlite");
    if (!journal) return journal.error();
    st->journal_ = std::move(*journal);
    st->notifier_ = std::make_unique<Notifier>(*st->journal_);
    for (auto& channel : st->parts_.alertChannels) st->notifier_->addChannel(std::move(channel));
    auto stack = openAtlasStack(st->parts_.settings, st->parts_.stateDir);
    if (!stack) return stack.error();
    st->stack_ = std::move(*stack);
    for (const auto& s : st->stack_.slices) st->slicePositionsUm_.push_back(s.positionUm);

    // Temporary files of writes a crash interrupted are never referenced: remove them (every
    // writer's naming scheme, anywhere in the state directory; nothing writes yet).
    if (auto removed = removeTemporaryFiles(st->parts_.stateDir); !removed)
        std::cerr << "<4>" << removed.error().message << std::endl;
    // A run left "running" means the daemon did not stop cleanly (crash, kill, watchdog).
    if (auto runs = st->journal_->runs()) {
        for (const auto& r : *runs)
            if (r.state == RunState::Running && !std::filesystem::exists(st->parts_.stateDir / "clean-stop"))
                (void)st->notifier_->raise("restarted", "warning",
                                           "the daemon restarted while run " + std::to_string(r.id) + " \"" +
                                               r.name + "\" was in progress (crash, power cut or watchdog); resuming it",
                                           r.id);
    }
    std::filesystem::remove(st->parts_.stateDir / "clean-stop", ec);

    st->worker_ = std::make_unique<RegistrationWorker>(*st->journal_, *st->notifier_, st->stack_,
                                                       st->parts_.stateDir, st->stats_);
    ScannerDeps deps{*st->parts_.stage, *st->parts_.camera, *st->journal_, *st->notifier_, *st->worker_,
                     st->stats_,        st->parts_.stateDir, st->parts_.freeSpace, st->parts_.watchdog,
                     st->parts_.status, st->parts_.stageMoved};
    st->scanner_ = std::make_unique<Scanner>(std::move(deps));
    return st;
}

Station::~Station() { stop(); }

void Station::start() {
    worker_->start();
    if (auto waiting = journal_->capturesAwaitingRegistration())
        for (auto id : *waiting) worker_->enqueue(id);
    scanner_->start();
}

void Station::stop() noexcept {
    if (!scanner_) return;
    scanner_->shutdown();
    worker_->stop();
    // Marks the stop as clean, so the next start raises no "restarted" alert.
    std::error_code ec;
    if (FILE* f = std::fopen((parts_.stateDir / "clean-stop").c_str(), "w")) std::fclose(f);
    (void)ec;
}

Result<std::int64_t> Station::submitPlan(const nlohmann::json& doc, const std::string& origin) {
    auto plan = parseScanPlan(doc, origin);
    if (!plan) return plan.error();
    if (auto r = resolveScanPlan(*plan, parts_.stage->limits(), slicePositionsUm_, origin); !r) return r.error();
    std::vector<PlannedSection> sections;
    for (const auto& ps : plan->sections) sections.push_back(ps.section);
    auto id = journal_->createRun(plan->name, plan->document, toJson(parts_.settings.scan), sections);
    if (!id) return id;
    notifier_->publish({"run_state", {{"run_id", *id}, {"state", "queued"}, {"reason", "submitted"}}});
    scanner_->wake();
    return id;
}

Result<void> Station::requestRescan(std::int64_t sectionId) {
    auto r = journal_->requestRescan(sectionId);
    if (!r) return r;
    notifier_->publish({"section_rescan", {{"section_id", sectionId}}});
    scanner_->wake();
    return {};
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
    if (auto a = journal_->alerts(true)) j["open_alerts"] = a->size();
    if (auto f = parts_.freeSpace(parts_.stateDir)) j["free_mb"] = static_cast<double>(*f) / (1 << 20);
    j["phases"] = stats_.summary();
    if (active)
        if (auto r = journal_->run(*active)) j["run"] = toJson(*r);
    return j;
}

Result<nlohmann::json> Station::sectionDetail(std::int64_t sectionId) {
    auto s = journal_->section(sectionId);
    if (!s) return s.error();
    nlohmann::json j = toJson(*s);
    auto caps = journal_->captures(sectionId);
    if (!caps) return caps.error();
    auto regs = journal_->registrations(sectionId);
    if (!regs) return regs.error();
    j["captures"] = nlohmann::json::array();
    for (const auto& c : *caps) j["captures"].push_back(toJson(c));
    j["registrations"] = nlohmann::json::array();
    for (const auto& r : *regs) {
        nlohmann::json rj = toJson(r);
        if (r.result.contains("damage_regions")) rj["damage_regions"] = r.result["damage_regions"];
        if (r.result.contains("regions")) rj["regions"] = r.result["regions"];
        if (r.result.contains("quality")) rj["quality_detail"] = r.result["quality"];
        j["registrations"].push_back(rj);
    }
    return j;
}

namespace {
std::string csvField(const std::string& s) {
    if (s.find_first_of(",\"\n") == std::string::npos) return s;
    std::string out = "\"";
    for (char c : s) out += c == '"' ? std::string("\"\"") : std::string(1, c);
    return out + "\"";
}
} // namespace

Result<std::string> Station::exportRun(std::int64_t runId, const std::string& format) {
    if (format != "json" && format != "csv")
        return makeError(ErrorCode::InvalidArgument, "format: expected \"json\" or \"csv\", got \"" + format + "\"");
    auto run = journal_->run(runId);
    if (!run) return run.error();
    auto secs = journal_->sections(runId);
    if (!secs) return secs.error();
    nlohmann::json rows = nlohmann::json::array();
    for (const auto& s : *secs) {
        nlohmann::json row{{"run_id", runId}, {"slide", s.slideName}, {"section", s.name},
                           {"section_id", s.id}, {"state", toString(s.state)}, {"attempts", s.attempts}};
        row["expected_slice"] = s.expectedSlice ? nlohmann::json(*s.expectedSlice) : nlohmann::json();
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
                        row["matched_slice"] = r.matchedSlice ? nlohmann::json(*r.matchedSlice) : nlohmann::json();
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
    if (format == "json") return nlohmann::json{{"run", toJson(*run)}, {"sections", rows}}.dump(2) + "\n";
    static const char* cols[] = {"run_id", "slide", "section", "section_id", "state", "attempts",
                                 "image", "stage_x_um", "stage_y_um", "stage_z_um", "um_per_px",
                                 "focus_found", "expected_slice", "atlas_slice", "matched_slice",
                                 "quality", "damaged", "damage_fraction", "damage_summary", "warning",
                                 "overlay"};
    std::ostringstream os;
    for (std::size_t i = 0; i < std::size(cols); ++i) os << (i ? "," : "") << cols[i];
    os << "\n";
    for (const auto& row : rows) {
        for (std::size_t i = 0; i < std::size(cols); ++i) {
            if (i) os << ",";
            if (!row.contains(cols[i]) || row[cols[i]].is_null()) continue;
            const auto& v = row[cols[i]];
            os << csvField(v.is_string() ? v.get<std::string>() : v.dump());
        }
        os << "\n";
    }
    return os.str();
}

std::shared_ptr<const hw::Frame> Station::liveFrame() const {
    std::lock_guard lock(liveMutex_);
    return live_;
}

} // namespace slicestation::daemon
