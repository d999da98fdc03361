#include "slicestation/daemon/station/series_tracker.hpp"

#include "slicestation/core/image_file.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <string>

namespace slicestation::daemon {

SeriesTracker::SeriesTracker(Journal& journal, const AtlasStack& stack,
                             const std::vector<pipeline::SliceFeatures>& slices,
                             std::filesystem::path stateDir)
    : journal_(journal), stack_(stack), slices_(slices), stateDir_(std::move(stateDir)) {}

double SeriesTracker::planIntervalUm(const std::vector<SectionRecord>& sections,
                                     const AtlasStack& stack) {
    std::vector<double> steps;
    std::optional<double> previous;
    for (const SectionRecord& s : sections) {
        if (!s.expectedSlice || *s.expectedSlice < 0 ||
            *s.expectedSlice >= static_cast<int>(stack.slices.size())) {
            previous.reset(); // only neighbours in the plan give a step
            continue;
        }
        const double at = stack.slices[static_cast<std::size_t>(*s.expectedSlice)].positionUm;
        if (previous && std::abs(at - *previous) > 0)
            steps.push_back(std::abs(at - *previous));
        previous = at;
    }
    if (steps.empty())
        return 0;
    std::nth_element(steps.begin(), steps.begin() + static_cast<long>(steps.size() / 2),
                     steps.end());
    return steps[steps.size() / 2];
}

int SeriesTracker::nearestSlice(const AtlasStack& stack, double positionUm) {
    int best = 0;
    for (std::size_t i = 0; i < stack.slices.size(); ++i)
        if (std::abs(stack.slices[i].positionUm - positionUm) <
            std::abs(stack.slices[static_cast<std::size_t>(best)].positionUm - positionUm))
            best = static_cast<int>(i);
    return best;
}

core::Result<pipeline::SectionFeatures>
SeriesTracker::featuresOf(const CaptureRecord& capture) const {
    auto image = core::readImage(stateDir_ / capture.imagePath);
    if (!image)
        return image.error();
    return pipeline::sectionFeatures(*image, capture.umPerPx, slices_.front().workUmPerPx);
}

core::Result<pipeline::SectionMatch>
SeriesTracker::matchWhole(const pipeline::SectionFeatures& f) const {
    // The whole stack: a section outside the series must show where it belongs.
    return pipeline::matchSection(f, slices_, {});
}

SeriesPlacement SeriesTracker::wordOn(std::size_t entry) const {
    const pipeline::SeriesFit& fit = matcher_->fit();
    const pipeline::SeriesSectionFit& s = fit.sections[entry];
    SeriesPlacement p;
    p.positionUm = s.positionUm;
    p.slot = s.slot;
    p.anomaly = std::string(pipeline::toString(s.anomaly));
    p.missingBefore = s.missingBefore;
    p.tiltLrDeg = fit.tiltColumnsDeg;
    p.tiltDvDeg = fit.tiltRowsDeg;
    if (s.anomaly == pipeline::SeriesAnomaly::Skipped) {
        // Planned sections that failed between the one before and this one held those slots:
        // they were mounted and planned, just not matched, so their gap is not a skip.
        const std::size_t from = entry > 0 ? entries_[entry - 1].planIndex + 1 : 0;
        int failed = 0;
        for (std::size_t k = from; k < entries_[entry].planIndex; ++k)
            failed += planFailed_[k] ? 1 : 0;
        p.missingBefore = std::max(0, s.missingBefore - failed);
        if (p.missingBefore == 0)
            p.anomaly = std::string(pipeline::toString(pipeline::SeriesAnomaly::None));
    }
    return p;
}

std::vector<int> SeriesTracker::plannedSlices(std::size_t planIndex) const {
    std::vector<int> out;
    const std::optional<int>& planned =
        planIndex < planSlices_.size() ? planSlices_[planIndex] : std::nullopt;
    if (!planned)
        return out;
    for (int s = *planned - 1; s <= *planned + 1; ++s)
        if (s >= 0 && s < static_cast<int>(stack_.slices.size()))
            out.push_back(s);
    return out;
}

std::optional<int> SeriesTracker::expectedSlice(std::size_t entry) const {
    const Entry& e = entries_[entry];
    const std::optional<int>& planned = planSlices_[e.planIndex];
    if (!planned || *planned < 0 || *planned >= static_cast<int>(stack_.slices.size()))
        return std::nullopt;
    // The model numbers slots from the first section's (canonically its index), the plan by its
    // entries (failed ones included): the difference is how many slots the cutting sequence has
    // gained on the plan by now, i.e. the skips (a swap's two partners move one each way).
    const pipeline::SeriesFit& fit = matcher_->fit();
    const auto planSteps = static_cast<int>(e.planIndex - entries_.front().planIndex);
    const int shift = fit.sections[entry].slot - planSteps;
    return nearestSlice(stack_, stack_.slices[static_cast<std::size_t>(*planned)].positionUm +
                                    shift * fit.spacingUm);
}

core::Result<void> SeriesTracker::reset(const RunRecord& run) {
    runId_ = 0;
    entries_.clear();
    planOrder_.clear();
    planSlices_.clear();
    planFailed_.clear();
    finished_ = false;
    matcher_.reset();
    volumeRefused_ = false; // a volume fixed since the last run is read again
    nextTiltAt_ = kTiltFirstSections;
    tilt_.reset();
    auto sections = journal_.sections(run.id);
    if (!sections)
        return sections.error();
    for (const SectionRecord& s : *sections) {
        planOrder_.push_back(s.id);
        planSlices_.push_back(s.expectedSlice);
        planFailed_.push_back(s.state == SectionState::Failed);
    }
    pipeline::SeriesMatchOptions options;
    options.model.intervalUm = planIntervalUm(*sections, stack_);
    matcher_ = std::make_unique<pipeline::SeriesMatcher>(slices_, options);
    runId_ = run.id;
    return {};
}

core::Result<SeriesTracker::Placement> SeriesTracker::place(const RunRecord& run,
                                                            const SectionRecord& section,
                                                            const CaptureRecord& capture,
                                                            bool tilted) {
    if (slices_.empty())
        return core::makeError(core::ErrorCode::InvalidArgument, "empty atlas stack");
    const bool rebuild = run.id != runId_ || !matcher_;
    if (rebuild)
        if (auto r = reset(run); !r)
            return r.error();
    const auto planAt = std::find(planOrder_.begin(), planOrder_.end(), section.id);
    if (planAt == planOrder_.end())
        return core::makeError(core::ErrorCode::NotFound, "section " + std::to_string(section.id) +
                                                              " is not in run " +
                                                              std::to_string(run.id));
    const auto planIndex = static_cast<std::size_t>(planAt - planOrder_.begin());
    if (rebuild) {
        // After a restart: the sections journalled before this one, in plan order, through the
        // model again (their word was settled and alerted before).
        for (std::size_t k = 0; k < planIndex; ++k) {
            auto regs = journal_.registrations(planOrder_[k]);
            if (!regs || regs->empty())
                continue;
            auto cap = journal_.capture(regs->front().captureId);
            auto f = cap ? featuresOf(*cap) : core::Result<pipeline::SectionFeatures>(cap.error());
            if (!f || !matcher_->add(*f, plannedSlices(k)))
                continue; // a section that cannot be matched again is left out, as it was then
            entries_.push_back({planOrder_[k], k, regs->front().id, regs->front().atlasSlice,
                                regs->front().matchedSlice.value_or(0), true, std::move(*f)});
        }
    }
    auto features = featuresOf(capture);
    if (!features)
        return features.error();
    Placement out;
    const auto known = std::find_if(entries_.begin(), entries_.end(),
                                    [&](const Entry& e) { return e.sectionId == section.id; });
    if (known != entries_.end() || (!entries_.empty() && entries_.back().planIndex > planIndex)) {
        // A rescan keeps its place in the model; a late section stays out of it.
        auto m = matchWhole(*features);
        if (!m)
            return m.error();
        out.matchedSlice = m->index;
        out.matchedPositionUm = m->positionUm;
        out.positionUm = m->positionUm;
        if (known != entries_.end()) {
            out.series = wordOn(static_cast<std::size_t>(known - entries_.begin()));
            out.positionUm = out.series->positionUm;
        }
        out.slice = nearestSlice(stack_, out.positionUm);
        if (tilted)
            applyTilt(out);
        return out;
    }
    auto m = matcher_->add(*features, plannedSlices(planIndex));
    if (!m)
        return m.error();
    out.matchedSlice = m->index;
    out.matchedPositionUm = m->positionUm;
    entries_.push_back({section.id, planIndex, 0, 0, m->index, false, std::move(*features)});
    out.series = wordOn(entries_.size() - 1);
    out.positionUm = out.series->positionUm;
    out.slice = nearestSlice(stack_, out.positionUm);
    entries_.back().registeredSlice = out.slice;
    out.expectedSlice = expectedSlice(entries_.size() - 1);
    if (tilted) {
        out.tiltNews = searchTiltIfDue();
        applyTilt(out);
    }
    return out;
}

std::string SeriesTracker::searchTiltIfDue() {
    const pipeline::SeriesFit& fit = matcher_->fit();
    if (volumeRefused_ || fit.inliers < nextTiltAt_)
        return {};
    if (!volume_) {
        auto v = readStackVolume(stack_);
        if (!v) {
            volumeRefused_ = true;
            return "the sections stay on the stack's straight slices: " + v.error().message;
        }
        volume_ = std::move(*v);
    }
    nextTiltAt_ = fit.inliers < 8 ? 8 : (3 * fit.inliers + 1) / 2; // 6, 8, 12, 18, 27, ...
    const auto t0 = std::chrono::steady_clock::now();
    const std::vector<pipeline::SectionFeatures> sections = modelFeatures();
    const double workUm = slices_.front().workUmPerPx;
    const pipeline::PlaneFeatures planes = [this, workUm](double pos, double lr, double dv) {
        return stackPlaneFeatures(*volume_, pos, lr, dv, workUm);
    };
    auto e = pipeline::searchSeriesTilt(sections, matcher_->matches(), fit, planes);
    const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    if (!e) // the earlier answer (or none) stands
        return "the tilt search failed: " + e.error().message;
    tilt_ = *e;
    const bool applied = tiltApplies();
    char text[256];
    std::snprintf(text, sizeof text,
                  "the brain's cutting angle from tilted planes: LR %.2f DV %.2f deg (%d sections "
                  "on the line, %d tilts, %.1f s); %s",
                  e->tiltColumnsDeg, e->tiltRowsDeg, fit.inliers, e->tiltsScored, s,
                  applied ? "sections are registered to planes cut at that angle"
                          : "within 0.5 deg of the stack's slices: they are used");
    return text;
}

bool SeriesTracker::tiltApplies() const {
    if (!tilt_ || !volume_)
        return false;
    // The stack's own slices may have been cut at a tilt (atlas slice --tilt-*-deg).
    const auto stackTilt = [this](const char* key) {
        const nlohmann::json& src = stack_.source;
        return src.is_object() && src.contains(key) && src[key].is_number() ? src[key].get<double>()
                                                                            : 0.0;
    };
    const double lr = stackTilt("tilt_lr_deg"), dv = stackTilt("tilt_dv_deg");
    return std::max(std::abs(tilt_->tiltColumnsDeg - lr), std::abs(tilt_->tiltRowsDeg - dv)) >=
           kMinAppliedTiltDeg;
}

void SeriesTracker::applyTilt(Placement& out) const {
    if (!tiltApplies())
        return;
    out.tiltLrDeg = tilt_->tiltColumnsDeg;
    out.tiltDvDeg = tilt_->tiltRowsDeg;
}

core::Result<pipeline::AtlasSlice> SeriesTracker::cutPlane(double positionUm, double tiltLrDeg,
                                                           double tiltDvDeg) const {
    if (!volume_)
        return core::makeError(core::ErrorCode::InvalidArgument,
                               "the stack's volume has not been read");
    return cutStackPlane(*volume_, positionUm, tiltLrDeg, tiltDvDeg);
}

void SeriesTracker::recorded(std::int64_t sectionId, std::int64_t registrationId,
                             int registeredSlice) {
    for (Entry& e : entries_)
        if (e.sectionId == sectionId && e.registrationId == 0) {
            e.registrationId = registrationId;
            e.registeredSlice = registeredSlice;
        }
}

void SeriesTracker::failed(std::int64_t runId, std::int64_t sectionId) {
    // Another run's (or before this run's first section reached the model): reset() reads the
    // failed state from the journal.
    if (runId != runId_)
        return;
    const auto at = std::find(planOrder_.begin(), planOrder_.end(), sectionId);
    const bool inModel = std::any_of(entries_.begin(), entries_.end(),
                                     [&](const Entry& e) { return e.sectionId == sectionId; });
    if (at != planOrder_.end() && !inModel)
        planFailed_[static_cast<std::size_t>(at - planOrder_.begin())] = true;
}

void SeriesTracker::finishRun() {
    if (finished_ || entries_.empty())
        return;
    finished_ = true;
    // On failure the live fit stands (finish refits only after its own matches succeed).
    (void)matcher_->finish(modelFeatures());
}

std::vector<pipeline::SectionFeatures> SeriesTracker::modelFeatures() const {
    std::vector<pipeline::SectionFeatures> features;
    for (const Entry& e : entries_)
        features.push_back(e.features);
    return features;
}

std::vector<SeriesTracker::Settled> SeriesTracker::settle(std::int64_t runId, bool runComplete) {
    std::vector<Settled> out;
    if (runId != runId_ || !matcher_)
        return out;
    const auto settleUpTo = [&](std::size_t end) {
        for (std::size_t k = 0; k < end; ++k) {
            Entry& e = entries_[k];
            if (e.settled)
                continue;
            e.settled = true;
            Settled s;
            s.sectionId = e.sectionId;
            s.registrationId = e.registrationId;
            s.series = wordOn(k);
            s.slice = nearestSlice(stack_, s.series.positionUm);
            s.registeredSlice = e.registeredSlice;
            s.matchedSlice = e.matchedSlice;
            s.expectedSlice = expectedSlice(k);
            out.push_back(s);
        }
    };
    // The sections the newest confirms keep the live word they were registered with; finish()
    // gives the final word to the run's last section, which nothing after it confirms (finish
    // may move earlier ones too, but they were registered and alerted on their live word).
    settleUpTo(entries_.empty() ? 0 : entries_.size() - 1);
    if (runComplete) {
        finishRun();
        settleUpTo(entries_.size());
    }
    return out;
}

} // namespace slicestation::daemon
