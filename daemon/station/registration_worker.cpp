#include "slicestation/daemon/station/registration_worker.hpp"

#include "slicestation/core/atomic_file.hpp"
#include "slicestation/core/image_file.hpp"
#include "slicestation/daemon/config/daemon_settings.hpp"
#include "slicestation/daemon/station/cell_counts.hpp"
#include "slicestation/daemon/station/damage_context.hpp"
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
      stats_(stats), series_(journal, stack, features_, stateDir_) {}

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
                if (auto sec = journal_.section(c->sectionId))
                    series_.failed(sec->runId, c->sectionId);
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

core::Result<void> RegistrationWorker::loadFeatures() {
    // The stack's matching features are computed once and kept: they do not change.
    if (!features_.empty())
        return {};
    auto f = stackFeatures(stack_);
    if (!f)
        return f.error();
    if (f->empty())
        return core::makeError(core::ErrorCode::InvalidArgument, "empty atlas stack");
    features_ = std::move(*f);
    return {};
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

/// The registration of `image` (at `umPerPx`, 0 unknown) to stack slice `slice` (its labels at
/// `atlas`), its outputs named from `base`: .result.json, .overlay.png, .labels.tif.
RegisterRequest stationRequest(const AtlasStack& stack, int slice, std::filesystem::path atlas,
                               std::filesystem::path image, double umPerPx,
                               const std::filesystem::path& base) {
    RegisterRequest rq;
    rq.atlas = std::move(atlas);
    rq.image = std::move(image);
    rq.imageUmPerPx = umPerPx;
    if (umPerPx > 0)
        rq.atlasUmPerPx = stack.slices[static_cast<std::size_t>(slice)].umPerPx;
    rq.atlasSlice = sliceFrame(stack, slice);
    rq.stackRegions = stack.regions;
    rq.output = base.string() + ".result.json";
    rq.overlay = base.string() + ".overlay.png";
    rq.warpedLabels = base.string() + ".labels.tif";
    return rq;
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
RegistrationWorker::chooseSlice(const RunRecord& run, const SectionRecord& section,
                                const CaptureRecord& capture, const ScanSettings& settings) {
    SliceChoice choice;
    choice.slice = section.expectedSlice;
    if (!settings.checkAtlasMatch && choice.slice)
        return choice;
    PhaseTimer matchTimer(stats_, "atlas_match");
    auto placed = loadFeatures();
    core::Result<SeriesTracker::Placement> p =
        placed ? series_.place(run, section, capture, settings.tiltedPlanes)
               : core::Result<SeriesTracker::Placement>(placed.error());
    if (p && !p->tiltNews.empty())
        notifier_.publish({"series_tilt", {{"run_id", run.id}, {"message", p->tiltNews}}});
    if (!p) {
        if (!choice.slice)
            return core::makeError(p.error().code, "no atlas slice planned and matching failed: " +
                                                       p.error().message);
        return choice; // the plan's slice, unchecked
    }
    // The series model is the authority now (issue 19): the plan is what is compared with it.
    choice.placement = *p;
    choice.slice = p->slice;
    if (!section.expectedSlice)
        return choice;
    if (std::abs(p->slice - *section.expectedSlice) <= settings.mismatchToleranceSlices) {
        // Within the tolerance the plan stands: the difference is the match's noise, and a
        // section registered a few slices off its plane can look damaged (the daemon process
        // test's s3: 300 um off on the built-in atlas, flagged at score 0.58).
        choice.slice = section.expectedSlice;
        return choice;
    }
    char at[96];
    std::snprintf(at, sizeof at, " (%.0f um)", p->positionUm);
    // Off the plan by as much as the sections the model found skipped before it: the cutting
    // sequence ran ahead of the plan, not a mounting mistake of this section.
    const bool skipsExplain =
        p->expectedSlice && *p->expectedSlice != *section.expectedSlice &&
        std::abs(p->slice - *p->expectedSlice) <= settings.mismatchToleranceSlices;
    choice.warning = "the series places the section at atlas slice " + std::to_string(p->slice) +
                     at + ", not the planned " + std::to_string(*section.expectedSlice) +
                     (skipsExplain ? " (sections were skipped before it in the cutting order)"
                                   : " (mounted out of order?)") +
                     "; own match " + std::to_string(p->matchedSlice) + ", registered to slice " +
                     std::to_string(p->slice);
    return choice;
}

std::string RegistrationWorker::seriesAlertText(const std::string& label,
                                                const SeriesTracker::Settled& settled,
                                                std::optional<int> plannedSlice,
                                                int toleranceSlices) {
    const SeriesPlacement& w = settled.series;
    std::string finding;
    if (w.anomaly == "skipped-before")
        finding = std::to_string(w.missingBefore) + " section" +
                  (w.missingBefore == 1 ? " is" : "s are") +
                  " missing just before it in the cutting order (lost or mounted elsewhere?)";
    else if (w.anomaly == "swapped")
        finding = "it is swapped with its neighbour on the slide";
    else if (w.anomaly == "out-of-order")
        finding = "it is mounted out of the cutting order";
    else if (w.anomaly == "duplicate")
        finding = "it lies where another section of the run lies";
    // Off the plan once the model's skips are counted (expectedSlice): a lost section is one
    // alert, on the section after it, not one on every section that follows.
    const std::optional<int> expected =
        settled.expectedSlice ? settled.expectedSlice : plannedSlice;
    const bool offPlan = expected && std::abs(settled.slice - *expected) > toleranceSlices;
    if (finding.empty() && !offPlan)
        return "";
    char at[64];
    std::snprintf(at, sizeof at, "%.0f um", w.positionUm);
    std::string text = label + ": the series model places it at " + at + " (atlas slice " +
                       std::to_string(settled.slice) + ")";
    if (plannedSlice)
        text += ", planned slice " + std::to_string(*plannedSlice);
    if (!finding.empty())
        text += ": " + finding;
    return text + "; own match slice " + std::to_string(settled.matchedSlice) +
           ", registered to slice " + std::to_string(settled.registeredSlice) +
           ". Check the slide's order";
}

void RegistrationWorker::settleSeries(const RunRecord& run, bool runComplete, int toleranceSlices) {
    for (const SeriesTracker::Settled& s : series_.settle(run.id, runComplete)) {
        auto section = journal_.section(s.sectionId);
        if (!section)
            continue;
        const std::string label = sectionLabel(*section, run.id);
        if (s.registrationId != 0)
            if (auto u = journal_.updateSeries(s.registrationId, s.series); !u)
                (void)notifier_.raise(
                    AlertKind::JournalError, AlertSeverity::Critical,
                    label + ": cannot store the series placement: " + u.error().message, run.id,
                    s.sectionId);
        const std::string text = seriesAlertText(label, s, section->expectedSlice, toleranceSlices);
        if (!text.empty())
            (void)notifier_.raise(AlertKind::AtlasMismatch, AlertSeverity::Warning, text, run.id,
                                  s.sectionId);
    }
}

std::string RegistrationWorker::sectionLabel(const SectionRecord& section, std::int64_t runId) {
    return "section " + section.name + " (" + section.slideName + ", run " + std::to_string(runId) +
           ")";
}

void RegistrationWorker::setPlanes(RegistrationRecord& rec, const SectionRecord& section,
                                   const SliceChoice& choice) const {
    const auto positionOf = [this](int slice) {
        return stack_.slices[static_cast<std::size_t>(slice)].positionUm;
    };
    rec.atlasSlice = *choice.slice;
    rec.foundPositionUm = positionOf(*choice.slice);
    rec.plannedSlice = section.expectedSlice;
    if (section.expectedSlice && *section.expectedSlice >= 0 &&
        *section.expectedSlice < static_cast<int>(stack_.slices.size()))
        rec.plannedPositionUm = positionOf(*section.expectedSlice);
    if (choice.placement) {
        rec.matchedSlice = choice.placement->matchedSlice;
        rec.matchedPositionUm = choice.placement->matchedPositionUm;
        rec.series = choice.placement->series;
    }
    rec.warning = choice.warning;
    rec.foundTiltLrDeg = choice.tiltLrDeg;
    rec.foundTiltDvDeg = choice.tiltDvDeg;
}

void RegistrationWorker::useTiltedPlane(SliceChoice& choice, const std::filesystem::path& base,
                                        RegisterRequest& rq) const {
    const SeriesTracker::Placement* p = choice.placement ? &*choice.placement : nullptr;
    if (!p || (p->tiltLrDeg == 0 && p->tiltDvDeg == 0))
        return;
    const StackSlice& straight = stack_.slices[static_cast<std::size_t>(*choice.slice)];
    auto plane = series_.cutPlane(straight.positionUm, p->tiltLrDeg, p->tiltDvDeg);
    const std::filesystem::path labels = base.string() + ".plane.tif";
    const std::filesystem::path templ = base.string() + ".plane-template.tif";
    const std::filesystem::path ids = base.string() + ".plane-ids.tif";
    // Every id of the tilted plane when the straight slices keep theirs (a major-region stack).
    const bool withIds = plane && !straight.idsFile.empty() && !plane->ids.empty();
    core::Result<void> written =
        plane ? core::writeImage(labels, plane->labels) : core::Result<void>(plane.error());
    if (written && plane->intensity.empty() != straight.templateFile.empty())
        written = core::makeError(core::ErrorCode::InvalidArgument,
                                  "the tilted plane's template does not match the stack's");
    if (written && !plane->intensity.empty())
        written = core::writeImage(templ, plane->intensity);
    if (written && withIds)
        written = core::writeImage(ids, plane->ids);
    if (!written) {
        choice.warning += std::string(choice.warning.empty() ? "" : "; ") +
                          "registered to the straight slice: cannot use the tilted plane: " +
                          written.error().message;
        return;
    }
    rq.atlas = labels;
    if (!plane->intensity.empty())
        rq.atlasTemplate = templ;
    if (withIds)
        rq.atlasIds = ids;
    else
        rq.atlasSlice->idsFile.clear(); // the straight slice's ids are not this plane's
    rq.atlasSlice->geometry = plane->geometry;
    rq.atlasSlice->templateFile.clear();
    choice.tiltLrDeg = p->tiltLrDeg;
    choice.tiltDvDeg = p->tiltDvDeg;
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
    const std::string label = sectionLabel(*section, run->id);
    auto settings =
        scanSettingsFromJson(run->settings, "run " + std::to_string(run->id) + " settings");
    // The run's last section settles the series' word on every section (the newest included).
    auto planned = journal_.sections(run->id);
    const bool last = planned && !planned->empty() && planned->back().id == section->id;
    auto fail = [&](const std::string& why) {
        (void)journal_.failSection(section->id, why);
        series_.failed(run->id, section->id); // its slot was planned, not skipped
        (void)notifier_.raise(AlertKind::RegistrationFailed, AlertSeverity::Warning,
                              label + ": " + why, run->id, section->id);
        notifier_.publish({"section_failed", {{"section_id", section->id}, {"reason", why}}});
        if (settings)
            settleSeries(*run, last, settings->mismatchToleranceSlices);
    };
    if (!settings)
        return fail(settings.error().message);
    auto choice = chooseSlice(*run, *section, *capture, *settings);
    if (!choice)
        return fail(choice.error().message);
    const int slice = *choice->slice;
    auto atlas = stackSlicePath(stack_, slice);
    if (!atlas)
        return fail(atlas.error().message);

    // Outputs beside the image: <section>-a<attempt>.result.json, .overlay.png, .labels.tif
    // (and the tilted plane registered to, .plane.tif).
    const std::filesystem::path image = stateDir_ / capture->imagePath;
    const std::string stem =
        image.filename().string().substr(0, image.filename().string().find('.'));
    const std::filesystem::path base = image.parent_path() / stem;
    RegisterRequest rq = stationRequest(stack_, slice, *atlas, image, capture->umPerPx, base);
    rq.maxTurnDeg = settings->maxTurnDeg;
    useTiltedPlane(*choice, base, rq);
    auto result = registerSectionFiles(rq);
    if (!result)
        return fail("registration failed: " + result.error().message);
    // Issue 18, item 5: the run's earlier sections are the damage decision's context.
    judgeWithSeriesContext(*result, earlierDamageOutlines(journal_, run->id, section->id));

    const auto rel = [&](const std::filesystem::path& p) {
        return std::filesystem::relative(p, stateDir_).string();
    };
    RegistrationRecord rec;
    rec.captureId = captureId;
    setPlanes(rec, *section, *choice);
    applyFlagScore(rec, result->registration, settings->damageFlagScore);
    rec.damageFraction = result->registration.damageFraction;
    rec.summary = result->registration.damageSummary;
    rec.quality = result->registration.quality.tissueOverlap;
    rec.resultPath = rel(rq.output);
    rec.overlayPath = rel(*rq.overlay);
    rec.labelsPath = rel(*rq.warpedLabels);
    // result.json records the slice registered to; the planes go beside it (docs/atlas.md).
    result->document["plane"] = planeJson(rec);
    if (auto w = core::writeFileAtomically(rq.output, result->document.dump(2) + "\n"); !w)
        return fail("cannot write " + rq.output.string() + ": " + w.error().message);
    rec.result = result->document;
    rec.result["regions"] = regionsShown(result->warpedLabels, stack_);
    record(rec, *run, *section, label);
    settleSeries(*run, last, settings->mismatchToleranceSlices);

    // Cells per region (docs/cells.md), when the run asks for it: after the registration is
    // journaled, still on this thread, so neither the stage nor the section's state waits.
    if (settings->countCells) {
        PhaseTimer cellsTimer(stats_, "count_cells");
        CellCountJob job;
        job.image = image;
        job.atlas = rq.atlas;
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
    if (rec.series)
        series_.recorded(section.id, rec.id, rec.atlasSlice);
    nlohmann::json ev = toJson(rec);
    ev["section_id"] = section.id;
    ev["run_id"] = run.id;
    const bool check = rec.damageVerdict == "check_registration";
    notifier_.publish({rec.damaged ? "section_damaged"
                       : check     ? "section_check_registration"
                                   : "section_registered",
                       ev});
    // With a series word the plane's alert waits until the model has confirmed it (settleSeries).
    if (!rec.warning.empty() && !rec.series)
        (void)notifier_.raise(AlertKind::AtlasMismatch, AlertSeverity::Warning,
                              label + ": " + rec.warning, run.id, section.id);
    if (rec.damaged || check)
        (void)notifier_.raise(rec.damaged ? AlertKind::Damaged : AlertKind::CheckRegistration,
                              rec.damaged ? AlertSeverity::Critical : AlertSeverity::Warning,
                              damageAlertText(rec, label), run.id, section.id);
}

} // namespace slicestation::daemon
