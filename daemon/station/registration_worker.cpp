#include "slicestation/daemon/station/registration_worker.hpp"

#include "slicestation/core/image_file.hpp"
#include "slicestation/daemon/config/daemon_settings.hpp"
#include "slicestation/daemon/station/cell_counts.hpp"
#include "slicestation/daemon/station/registration_service.hpp"

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <map>

namespace slicestation::daemon {

RegistrationWorker::RegistrationWorker(Journal& journal, Notifier& notifier,
                                       const AtlasStack& stack, std::filesystem::path stateDir,
                                       PhaseStats& stats)
    : journal_(journal), notifier_(notifier), stack_(stack), stateDir_(std::move(stateDir)),
      stats_(stats) {}

RegistrationWorker::~RegistrationWorker() {
    stop();
}

void RegistrationWorker::start() {
    std::lock_guard lock(mutex_);
    if (thread_.joinable())
        return;
    stopping_ = false;
    thread_ = std::thread([this] { loop(); });
}

void RegistrationWorker::enqueue(std::int64_t captureId) {
    {
        std::lock_guard lock(mutex_);
        queue_.push_back(captureId);
    }
    cv_.notify_all();
}

bool RegistrationWorker::idle() const {
    std::lock_guard lock(mutex_);
    return queue_.empty() && !busy_;
}

bool RegistrationWorker::waitIdle(std::chrono::milliseconds timeout) const {
    std::unique_lock lock(mutex_);
    return cv_.wait_for(lock, timeout, [this] { return queue_.empty() && !busy_; });
}

void RegistrationWorker::stop() noexcept {
    {
        std::lock_guard lock(mutex_);
        stopping_ = true;
        queue_.clear();
    }
    cv_.notify_all();
    if (thread_.joinable())
        thread_.join();
}

void RegistrationWorker::loop() {
    for (;;) {
        std::int64_t id = 0;
        {
            std::unique_lock lock(mutex_);
            cv_.wait(lock, [this] { return stopping_ || !queue_.empty(); });
            if (stopping_)
                return;
            id = queue_.front();
            queue_.pop_front();
            busy_ = true;
        }
        try {
            process(id);
        } catch (const std::exception& e) {
            // Nothing may escape a thread entry; a library bug becomes a failed section.
            if (auto c = journal_.capture(id)) {
                (void)journal_.failSection(c->sectionId,
                                           std::string("registration crashed: ") + e.what());
                (void)notifier_.raise(AlertKind::RegistrationFailed, AlertSeverity::Warning,
                                      std::string("registration crashed: ") + e.what(),
                                      std::nullopt, c->sectionId);
            }
        }
        {
            std::lock_guard lock(mutex_);
            busy_ = false;
        }
        cv_.notify_all();
    }
}

core::Result<int> RegistrationWorker::matchToStack(const std::filesystem::path& image,
                                                   double umPerPx, std::optional<int> expected,
                                                   int window) {
    // The stack's matching features are computed once and kept: they do not change.
    if (features_.empty()) {
        auto f = stackFeatures(stack_);
        if (!f)
            return f.error();
        features_ = std::move(*f);
        if (features_.empty())
            return core::makeError(core::ErrorCode::InvalidArgument, "empty atlas stack");
    }
    auto img = core::readImage(image);
    if (!img)
        return img.error();
    pipeline::MatchOptions opt;
    if (expected) {
        opt.first = std::max(0, *expected - window);
        opt.last = std::min(static_cast<int>(features_.size()) - 1, *expected + window);
    }
    auto section = pipeline::sectionFeatures(*img, umPerPx, features_.front().workUmPerPx);
    if (!section)
        return section.error();
    auto m = pipeline::matchSection(*section, features_, opt);
    if (!m)
        return m.error();
    return m->index;
}

namespace {

/// The atlas regions a section shows (its warped labels), named from the stack's ontology,
/// largest first, each with its share of the brain in the section.
nlohmann::json regionsShown(const cv::Mat& labels, const AtlasStack& stack) {
    std::map<std::int32_t, std::int64_t> counts;
    std::int64_t inside = 0;
    for (int y = 0; y < labels.rows; ++y) {
        const auto* row = labels.ptr<std::int32_t>(y);
        for (int x = 0; x < labels.cols; ++x)
            if (row[x] > 0) {
                ++counts[row[x]];
                ++inside;
            }
    }
    std::vector<std::pair<std::int64_t, std::int32_t>> order;
    for (const auto& [regionId, n] : counts)
        order.push_back({n, regionId});
    std::sort(order.rbegin(), order.rend());
    nlohmann::json regions = nlohmann::json::array();
    for (const auto& [n, regionId] : order) {
        nlohmann::json r{{"id", regionId},
                         {"share", inside > 0 ? static_cast<double>(n) / inside : 0.0}};
        if (const StackRegion* sr = findRegion(stack, static_cast<std::uint32_t>(regionId))) {
            r["name"] = sr->name;
            r["acronym"] = sr->acronym;
            r["color"] = colorHex(sr->colorRgb);
        }
        regions.push_back(std::move(r));
    }
    return regions;
}

} // namespace

void RegistrationWorker::applyFlagScore(RegistrationRecord& rec, const pipeline::Registration& reg,
                                        double flagScore) {
    // The station decides damaged vs clean from the score with its own threshold (the run's
    // snapshot), so that a learned threshold takes effect without touching the pipeline. The
    // pipeline's "check the registration" stays a third state: the deficit may be misfit.
    rec.damageScore = reg.damageScore;
    rec.flagScore = flagScore;
    if (reg.damageVerdict == pipeline::DamageVerdict::CheckRegistration)
        rec.damageVerdict = "check_registration";
    else
        rec.damageVerdict = reg.damageScore >= flagScore ? "damaged" : "clean";
    rec.damaged = rec.damageVerdict == "damaged";
}

std::string RegistrationWorker::damageAlertText(const RegistrationRecord& rec,
                                                const std::string& label) {
    char score[32];
    std::snprintf(score, sizeof score, "%.2f", rec.damageScore.value_or(0.0));
    const std::string detail = rec.summary.empty() ? "" : ": " + rec.summary;
    if (rec.damageVerdict == "check_registration")
        return "check the registration of " + label +
               ": tissue looks missing where the atlas fit is uncertain (score " + score + detail +
               "); look at the overlay, then rescan or accept it";
    return label + " is damaged, score " + score + detail +
           ": re-mount it and request a rescan, or accept it as is";
}

core::Result<RegistrationWorker::SliceChoice>
RegistrationWorker::chooseSlice(const SectionRecord& section, const CaptureRecord& capture,
                                const ScanSettings& settings) {
    SliceChoice choice;
    choice.slice = section.expectedSlice;
    if (!settings.checkAtlasMatch && choice.slice)
        return choice;
    PhaseTimer matchTimer(stats_, "atlas_match");
    // The whole stack is searched: a section mounted far out of order must show where it belongs.
    auto m = matchToStack(stateDir_ / capture.imagePath, capture.umPerPx, std::nullopt, 0);
    if (!m) {
        if (!choice.slice)
            return core::makeError(m.error().code, "no atlas slice planned and matching failed: " +
                                                       m.error().message);
        return choice;
    }
    choice.matched = *m;
    if (!choice.slice) {
        choice.slice = *m;
    } else if (std::abs(*m - *choice.slice) > settings.mismatchToleranceSlices) {
        choice.warning = "the section matches atlas slice " + std::to_string(*m) +
                         ", not the planned " + std::to_string(*choice.slice) +
                         " (mounted out of order?); registered to the planned slice";
    }
    return choice;
}

void RegistrationWorker::process(std::int64_t captureId) {
    PhaseTimer timer(stats_, "register");
    auto capture = journal_.capture(captureId);
    if (!capture)
        return;
    auto section = journal_.section(capture->sectionId);
    if (!section || section->state != SectionState::Captured)
        return; // a rescan overtook it
    auto run = journal_.run(section->runId);
    if (!run)
        return;
    const std::string label = "section " + section->name + " (" + section->slideName + ", run " +
                              std::to_string(run->id) + ")";
    auto fail = [&](const std::string& why) {
        (void)journal_.failSection(section->id, why);
        (void)notifier_.raise(AlertKind::RegistrationFailed, AlertSeverity::Warning,
                              label + ": " + why, run->id, section->id);
        notifier_.publish({"section_failed", {{"section_id", section->id}, {"reason", why}}});
    };
    auto settings =
        scanSettingsFromJson(run->settings, "run " + std::to_string(run->id) + " settings");
    if (!settings)
        return fail(settings.error().message);
    auto choice = chooseSlice(*section, *capture, *settings);
    if (!choice)
        return fail(choice.error().message);
    const int slice = *choice->slice;
    auto atlas = stackSlicePath(stack_, slice);
    if (!atlas)
        return fail(atlas.error().message);

    // Outputs beside the image: <section>-a<attempt>.result.json, .overlay.png, .labels.tif.
    const std::filesystem::path image = stateDir_ / capture->imagePath;
    const std::string stem =
        image.filename().string().substr(0, image.filename().string().find('.'));
    const std::filesystem::path base = image.parent_path() / stem;
    RegisterRequest rq;
    rq.atlas = *atlas;
    rq.image = image;
    rq.imageUmPerPx = capture->umPerPx;
    rq.maxTurnDeg = settings->maxTurnDeg;
    if (rq.imageUmPerPx > 0)
        rq.atlasUmPerPx = stack_.slices[static_cast<std::size_t>(slice)].umPerPx;
    rq.atlasSlice = sliceFrame(stack_, slice);
    rq.output = base.string() + ".result.json";
    rq.overlay = base.string() + ".overlay.png";
    rq.warpedLabels = base.string() + ".labels.tif";
    auto result = registerSectionFiles(rq);
    if (!result)
        return fail("registration failed: " + result.error().message);

    const auto rel = [&](const std::filesystem::path& p) {
        return std::filesystem::relative(p, stateDir_).string();
    };
    RegistrationRecord rec;
    rec.captureId = captureId;
    rec.atlasSlice = slice;
    rec.matchedSlice = choice->matched;
    rec.warning = choice->warning;
    applyFlagScore(rec, result->registration, settings->damageFlagScore);
    rec.damageFraction = result->registration.damageFraction;
    rec.summary = result->registration.damageSummary;
    rec.quality = result->registration.quality.tissueOverlap;
    rec.resultPath = rel(rq.output);
    rec.overlayPath = rel(*rq.overlay);
    rec.labelsPath = rel(*rq.warpedLabels);
    rec.result = result->document;
    rec.result["regions"] = regionsShown(result->warpedLabels, stack_);
    record(rec, *run, *section, label);

    // Cells per region (docs/cells.md), when the run asks for it: after the registration is
    // journaled, still on this thread, so neither the stage nor the section's state waits.
    if (settings->countCells) {
        PhaseTimer cellsTimer(stats_, "count_cells");
        CellCountJob job;
        job.image = image;
        job.atlas = *atlas;
        job.base = base;
        job.runDir = stateDir_ / "runs" / std::to_string(run->id);
        job.ontologyFile = settings->cellsOntology;
        job.options.detector.channel = settings->cellsChannel;
        job.options.cellDiameterUm = settings->cellDiameterUm;
        job.options.imageUmPerPx = capture->umPerPx;
        auto counted = countCellsBeside(result->registration, job);
        nlohmann::json ev = counted ? *counted : nlohmann::json{{"error", counted.error().message}};
        ev["section_id"] = section->id;
        ev["run_id"] = run->id;
        notifier_.publish({counted ? "cells_counted" : "cells_count_failed", ev});
    }
}

void RegistrationWorker::record(RegistrationRecord& rec, const RunRecord& run,
                                const SectionRecord& section, const std::string& label) {
    auto id = journal_.recordRegistration(rec);
    if (!id) {
        (void)notifier_.raise(AlertKind::JournalError, AlertSeverity::Critical,
                              label + ": cannot store registration: " + id.error().message, run.id,
                              section.id);
        return;
    }
    rec.id = *id;
    nlohmann::json ev = toJson(rec);
    ev["section_id"] = section.id;
    ev["run_id"] = run.id;
    const bool check = rec.damageVerdict == "check_registration";
    notifier_.publish({rec.damaged ? "section_damaged"
                       : check     ? "section_check_registration"
                                   : "section_registered",
                       ev});
    if (!rec.warning.empty())
        (void)notifier_.raise(AlertKind::AtlasMismatch, AlertSeverity::Warning,
                              label + ": " + rec.warning, run.id, section.id);
    if (rec.damaged || check)
        (void)notifier_.raise(rec.damaged ? AlertKind::Damaged : AlertKind::CheckRegistration,
                              rec.damaged ? AlertSeverity::Critical : AlertSeverity::Warning,
                              damageAlertText(rec, label), run.id, section.id);
}

} // namespace slicestation::daemon
