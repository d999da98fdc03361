#pragma once
// A station for the page's browser tests whose records and events the test sets by hand: one run
// (id 7) of four sections, alerts, a live frame with a stage position, images per section.
// Every control request is recorded (and changes the records as the real station would), and
// publish() sends an event to the page at the moment the test chooses, so the tests can space
// events 2 ms apart as the real station does, without scanning anything.
#include "slicestation/daemon/station/station_api.hpp"
#include "slicestation/daemon/storage/alert_kind.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <functional>
#include <mutex>
#include <string>
#include <vector>

namespace slicestation::testing_web {

using namespace slicestation::daemon;

/// The one place the tests build an alert record (kinds and severities are its strings).
inline AlertRecord makeAlert(std::int64_t id, std::optional<std::int64_t> section,
                             const std::string& kind, const std::string& severity,
                             const std::string& message, const std::string& raisedUtc) {
    AlertRecord a;
    a.id = id;
    a.runId = 7;
    a.sectionId = section;
    // The test's strings must name a kind and a severity the daemon knows.
    a.kind = parseAlertKind(kind).value();
    a.severity = parseAlertSeverity(severity).value();
    a.message = message;
    a.raisedUtc = raisedUtc;
    return a;
}

class ScriptedStation final : public StationApi {
public:
    static constexpr std::int64_t kRun = 7;

    ScriptedStation() {
        RunRecord old;
        old.id = 6;
        old.name = "mouse-41";
        old.state = RunState::Finished;
        old.createdUtc = "2026-12-01T08:00:00.000Z";
        old.startedUtc = "2026-12-01T08:00:05.000Z";
        old.endedUtc = "2026-12-01T08:40:00.000Z";
        old.sectionCount = old.doneCount = 12;
        RunRecord run;
        run.id = kRun;
        run.name = "mouse-42";
        run.state = RunState::Running;
        run.createdUtc = "2026-12-02T09:30:00.000Z";
        run.startedUtc = "2026-12-02T09:30:02.000Z";
        run.sectionCount = 4;
        runs_ = {old, run};
        for (int i = 0; i < 4; ++i) {
            SectionRecord s;
            s.id = 101 + i;
            s.runId = kRun;
            s.slideName = "slide-01";
            s.index = i;
            s.name = "s0" + std::to_string(i + 1);
            sections_.push_back(s);
        }
        auto f = std::make_shared<hw::Frame>(hw::PixelFormat::Mono8, 320, 240);
        f->metadata.stage = hw::StagePosition{12345.5, 6789.25, 150.0};
        frame_ = f;
    }

    // What the test does ---------------------------------------------------------------------
    /// Sends an event to every listener (the event stream), now.
    /// A "stage_position" is also the status's stage from then on, as the station keeps it.
    void publish(const std::string& type, const nlohmann::json& data) {
        std::vector<std::function<void(const StationEvent&)>> ls;
        {
            std::lock_guard lock(m_);
            ls = listeners_;
            if (type == "stage_position")
                stage_ = data;
        }
        for (auto& l : ls)
            l({type, data});
    }
    /// Records section `id` as captured and registered (damaged or not) with a damage fraction,
    /// and optionally the station's damage score and verdict (one tear region of that score).
    void registerSection(std::int64_t id, bool damaged, double damageFraction = 0,
                         std::optional<double> score = std::nullopt,
                         const std::string& verdict = "") {
        std::lock_guard lock(m_);
        SectionRecord& s = sectionRef(id);
        s.damageScore = score;
        s.damageVerdict = verdict;
        scores_[id] = {score, verdict};
        s.state = damaged ? SectionState::Damaged : SectionState::Registered;
        s.attempts = std::max(s.attempts, 1);
        runs_[1].doneCount = static_cast<int>(
            std::count_if(sections_.begin(), sections_.end(), [](const SectionRecord& x) {
                return x.state == SectionState::Registered || x.state == SectionState::Damaged;
            }));
        damage_[id] = damageFraction;
    }
    /// Section `id`'s COUNTS.csv (GET /api/sections/{id}/counts); the run's with setRunCounts.
    void setCounts(std::int64_t id, const std::string& csv) {
        std::lock_guard lock(m_);
        counts_[id] = csv;
    }
    void setRunCounts(const std::string& csv) {
        std::lock_guard lock(m_);
        runCounts_ = csv;
    }
    void addAlert(const AlertRecord& a) {
        std::lock_guard lock(m_);
        alerts_.push_back(a);
    }
    void setStatus(const std::string& state, const std::string& activity) {
        std::lock_guard lock(m_);
        state_ = state;
        activity_ = activity;
    }
    void setRunState(RunState s) {
        std::lock_guard lock(m_);
        runs_[1].state = s;
    }
    std::vector<std::string> calls() {
        std::lock_guard lock(m_);
        return calls_;
    }
    bool called(const std::string& c) {
        auto cs = calls();
        return std::find(cs.begin(), cs.end(), c) != cs.end();
    }

    // StationApi --------------------------------------------------------------------------------
    nlohmann::json status() override {
        std::lock_guard lock(m_);
        nlohmann::json j{{"state", state_}, {"activity", activity_}};
        j["active_run"] = state_ == "scanning" ? nlohmann::json(kRun) : nlohmann::json();
        if (state_ == "scanning")
            j["run"] = toJson(runs_[1]);
        j["simulated"] = {{"stage", true}, {"camera", true}};
        if (!stage_.is_null())
            j["stage"] = stage_;
        return j;
    }
    core::Result<std::vector<RunRecord>> runs() override {
        std::lock_guard lock(m_);
        return runs_;
    }
    core::Result<RunRecord> run(std::int64_t id) override {
        std::lock_guard lock(m_);
        for (const auto& r : runs_)
            if (r.id == id)
                return r;
        return core::makeError(core::ErrorCode::NotFound, "no run " + std::to_string(id));
    }
    core::Result<std::vector<SectionRecord>> sections(std::int64_t id) override {
        std::lock_guard lock(m_);
        if (id == kRun)
            return sections_;
        if (id == 6)
            return std::vector<SectionRecord>{};
        return core::makeError(core::ErrorCode::NotFound, "no run " + std::to_string(id));
    }
    core::Result<std::string> exportRun(std::int64_t, const std::string&) override {
        return std::string("{}");
    }
    core::Result<nlohmann::json> sectionDetail(std::int64_t id) override {
        std::lock_guard lock(m_);
        auto it = std::find_if(sections_.begin(), sections_.end(),
                               [&](const SectionRecord& s) { return s.id == id; });
        if (it == sections_.end())
            return core::makeError(core::ErrorCode::NotFound, "no section " + std::to_string(id));
        nlohmann::json j = toJson(*it);
        j["captures"] = nlohmann::json::array();
        j["registrations"] = nlohmann::json::array();
        if (it->attempts > 0) {
            CaptureRecord c;
            c.id = id * 10;
            c.sectionId = id;
            c.attempt = it->attempts;
            c.umPerPx = 10;
            c.stage = {1000.0 * static_cast<double>(id - 100), 2000, 150};
            c.focusFound = id != 102;
            c.focusScore = 0.25 * static_cast<double>(id - 100);
            c.capturedUtc = "2026-12-02T09:31:00.000Z";
            j["captures"].push_back(toJson(c));
        }
        if (damage_.count(id)) {
            RegistrationRecord r;
            r.id = id * 10;
            r.captureId = id * 10;
            r.atlasSlice = 40;
            r.damaged = it->state == SectionState::Damaged;
            r.damageFraction = damage_[id];
            r.summary = r.damaged ? "tear" : "";
            r.quality = 0.9;
            r.registeredUtc = "2026-12-02T09:31:05.000Z";
            r.damageScore = scores_[id].first;
            r.damageVerdict = scores_[id].second;
            if (r.damageScore)
                r.flagScore = 0.5;
            j["registrations"].push_back(toJson(r));
            if (r.damageScore)
                j["registrations"].back()["damage_regions"] = {
                    {{"kind", "tear"}, {"share", damage_[id]}, {"score", *r.damageScore - 0.12}}};
        }
        return j;
    }
    core::Result<std::string> sectionCounts(std::int64_t id) override {
        std::lock_guard lock(m_);
        auto it = counts_.find(id);
        if (it == counts_.end())
            return core::makeError(core::ErrorCode::NotFound, "no cell counts");
        return it->second;
    }
    core::Result<std::string> runCounts(std::int64_t id) override {
        std::lock_guard lock(m_);
        if (id != kRun || runCounts_.empty())
            return core::makeError(core::ErrorCode::NotFound, "no cell counts");
        return runCounts_;
    }
    core::Result<std::vector<AlertRecord>> alerts(bool openOnly) override {
        std::lock_guard lock(m_);
        std::vector<AlertRecord> out;
        for (const auto& a : alerts_)
            if (!openOnly || !a.acknowledgedUtc)
                out.push_back(a);
        return out;
    }
    std::shared_ptr<const hw::Frame> liveFrame() const override { return frame_; }
    /// A 2400x1600 image per section, its own grey level; the overlay draws a white frame.
    core::Result<cv::Mat> sectionImage(std::int64_t id, bool overlay) override {
        {
            std::lock_guard lock(m_);
            calls_.push_back("image " + std::to_string(id) + (overlay ? " overlay" : ""));
        }
        cv::Mat m(1600, 2400, CV_8UC3, cv::Scalar::all(static_cast<double>(40 * (id - 100))));
        if (overlay)
            cv::rectangle(m, {100, 100}, {2300, 1500}, cv::Scalar(255, 255, 255), 20);
        return m;
    }
    /// The pyramid of those images: 512 px tiles, levels 2400 x 1600 and 1200 x 800.
    core::Result<ImagePyramid> sectionPyramid(std::int64_t) override {
        return ImagePyramid{512, {{2400, 1600}, {1200, 800}}};
    }
    /// Tile (x, y) of a level: BGR (20 + 40 x, 20 + 40 y, 250 - 100 level), so that the page's
    /// pixels tell which tile was drawn where.
    core::Result<cv::Mat> sectionTile(std::int64_t id, int level, int x, int y) override {
        const cv::Size size = level == 0 ? cv::Size(2400, 1600) : cv::Size(1200, 800);
        if (level < 0 || level > 1 || x < 0 || y < 0 || x * 512 >= size.width ||
            y * 512 >= size.height)
            return core::makeError(core::ErrorCode::NotFound, "no such tile");
        {
            std::lock_guard lock(m_);
            calls_.push_back("tile " + std::to_string(id) + " " + std::to_string(level) + "/" +
                             std::to_string(x) + "_" + std::to_string(y));
        }
        return cv::Mat(std::min(512, size.height - 512 * y), std::min(512, size.width - 512 * x),
                       CV_8UC3, cv::Scalar(20 + 40 * x, 20 + 40 * y, 250 - 100 * level));
    }
    core::Result<RegionAtPixel> regionAt(std::int64_t, int x, int y, int) override {
        return RegionAtPixel{315, x, y, "Isocortex", "Isocortex"};
    }
    core::Result<std::int64_t> submitPlan(const nlohmann::json&, const std::string&) override {
        return std::int64_t{8};
    }
    core::Result<void> pauseRun(std::int64_t id) override {
        return control("pause", id, RunState::Running, RunState::Paused);
    }
    core::Result<void> resumeRun(std::int64_t id, bool reset) override {
        return control(reset ? "resume reset" : "resume", id, RunState::Paused, RunState::Running);
    }
    core::Result<void> cancelRun(std::int64_t id) override {
        return control("cancel", id, std::nullopt, RunState::Cancelled);
    }
    core::Result<void> requestRescan(std::int64_t id) override {
        std::lock_guard lock(m_);
        calls_.push_back("rescan " + std::to_string(id));
        sectionRef(id).state = SectionState::Rescan;
        return {};
    }
    core::Result<AlertRecord> acknowledgeAlert(std::int64_t id,
                                               const std::string& action) override {
        std::lock_guard lock(m_);
        for (auto& a : alerts_)
            if (a.id == id) {
                if (a.acknowledgedUtc)
                    return core::makeError(core::ErrorCode::InvalidArgument, "already answered");
                calls_.push_back("ack " + action + " " + std::to_string(id));
                a.acknowledgedUtc = "2026-12-02T09:40:00.000Z";
                a.ackAction = action;
                if (action == "rescan" && a.sectionId)
                    sectionRef(*a.sectionId).state = SectionState::Rescan;
                return a;
            }
        return core::makeError(core::ErrorCode::NotFound, "no alert " + std::to_string(id));
    }
    void addListener(std::function<void(const StationEvent&)> l) override {
        std::lock_guard lock(m_);
        listeners_.push_back(std::move(l));
    }

private:
    SectionRecord& sectionRef(std::int64_t id) {
        for (auto& s : sections_)
            if (s.id == id)
                return s;
        throw std::out_of_range("no section " + std::to_string(id));
    }
    core::Result<void> control(const std::string& name, std::int64_t id,
                               std::optional<RunState> from, RunState to) {
        std::lock_guard lock(m_);
        if (id != kRun)
            return core::makeError(core::ErrorCode::NotFound, "no run " + std::to_string(id));
        if (from && runs_[1].state != *from)
            return core::makeError(core::ErrorCode::InvalidArgument,
                                   std::string("run is ") + toString(runs_[1].state));
        calls_.push_back(name + " " + std::to_string(id));
        runs_[1].state = to;
        return {};
    }

    mutable std::mutex m_;
    nlohmann::json stage_; ///< the last "stage_position" published (null: none)
    std::string state_ = "scanning", activity_ = "capturing s01";
    std::vector<RunRecord> runs_;
    std::vector<SectionRecord> sections_;
    std::map<std::int64_t, double> damage_;
    std::map<std::int64_t, std::pair<std::optional<double>, std::string>> scores_;
    std::vector<AlertRecord> alerts_;
    std::map<std::int64_t, std::string> counts_;
    std::string runCounts_;
    std::vector<std::string> calls_;
    std::shared_ptr<const hw::Frame> frame_;
    std::vector<std::function<void(const StationEvent&)>> listeners_;
};

} // namespace slicestation::testing_web
