#pragma once
/// The series model of the run being registered (issue 19, item 4; docs/atlas.md, "The daemon:
/// the series model in a run"). The registration worker feeds each captured section to one
/// pipeline::SeriesMatcher per run, in scan (plan) order, with the plan's interval as the prior,
/// and gives the plane the model says: its position rounded to the stack's nearest slice (the
/// worker registers to it unless it lies within the tolerance of the planned slice).
///
/// Tilted planes (`[scan] tilted_planes`, on by default): once the model holds
/// kTiltFirstSections sections on its line, the brain's cutting angle is searched with planes
/// cut from the stack's volume (pipeline::searchSeriesTilt, 4-8 s, on this thread), and again
/// as the line grows: at 8 sections, then each time it has grown by half (12, 18, 27, ...; seven
/// searches in a run of 60), so the angle narrows as the run goes without a search per section.
/// While the found angle leans at least kMinAppliedTiltDeg on either axis, the placement carries it
/// and the worker registers to the plane cut at that angle through the chosen slice's position
/// (cutPlane). A stack not cut from a volume, or a volume that cannot be read, leaves the straight
/// slices (said once per run).
///
/// - A section already in the model (a rescan) keeps its place: it is matched on its own against
///   the whole stack and registered to the model's current position for it.
/// - A section that arrives after sections later in the plan (its first capture failed and was
///   rescanned) is not added (the model's slots follow arrival order): its own whole-stack match
///   is the found plane, and it has no series word.
/// - After a restart (or when another run's section arrives) the model is rebuilt from the run's
///   journalled sections before this one, matching their first registered images again.
/// - A planned section that failed (capture or registration) before it reached the model holds
///   its slot: the gap it leaves is not a skip (failed()).
///
/// The model's word on a section changes as later sections arrive (a swap first looks like a
/// skip), so settle() hands out each section's word once it is confirmed: when the next section
/// has been added, or at once for the run's last section: the sections before it are settled
/// with their live word (the one they were registered with), then the model's finish() runs
/// (each flagged section matched again at the place that would make the run regular), so the
/// last section's word is the model's final one.
///
/// Threading: the registration worker's thread only. Blocking: image reads and matching (about
/// 0.5 s per section; a rebuild costs that per journalled section).
#include "slicestation/core/result.hpp"
#include "slicestation/daemon/storage/atlas_stack.hpp"
#include "slicestation/daemon/storage/journal.hpp"
#include "slicestation/daemon/storage/stack_volume.hpp"
#include "slicestation/pipeline/atlas_matching.hpp"
#include "slicestation/pipeline/series_matching.hpp"

#include <cstdint>
#include <filesystem>
#include <memory>
#include <optional>
#include <string>
#include <vector>

namespace slicestation::daemon {

class SeriesTracker {
public:
    /// On-line sections before the first tilt search (the search uses the six best).
    static constexpr int kTiltFirstSections = 6;
    /// A found tilt within this of the stack's slices' tilt (0 unless the stack was cut tilted)
    /// on both axes is not applied: the search's own step
    /// (TiltSearchOptions::fineStepDeg), below which it cannot tell a tilt from none.
    static constexpr double kMinAppliedTiltDeg = 0.5;

    /// `stack` and `slices` (its matching features, stackFeatures) must outlive the tracker.
    SeriesTracker(Journal& journal, const AtlasStack& stack,
                  const std::vector<pipeline::SliceFeatures>& slices,
                  std::filesystem::path stateDir);

    /// Where a section lies and the slice to register it to.
    struct Placement {
        int slice = 0;         ///< the found plane: the stack slice nearest to positionUm
        double positionUm = 0; ///< the series' answer (or the own match without a series word)
        int matchedSlice = 0;  ///< the section's own match
        double matchedPositionUm = 0;
        std::optional<SeriesPlacement> series; ///< the model's word now; none when not in it
        std::optional<int> expectedSlice;      ///< as Settled::expectedSlice, the model's view now
        /// The tilt of the plane to register to, degrees (as `atlas slice --tilt-*-deg`); both
        /// 0: the stack's straight slice.
        double tiltLrDeg = 0, tiltDvDeg = 0;
        /// What a tilt search run for this placement found, or why tilted planes cannot be cut
        /// (once per run); empty otherwise. For the station's log and event stream.
        std::string tiltNews;
    };
    /// Matches the capture of `section` (of `run`) with the run's series model; with `tilted`
    /// (the run's tilted_planes) searches the brain's tilt when due and applies it.
    /// \return the errors of reading the image (NotFound, IoError), of matching (NoTissue,
    ///         InvalidArgument) and of the journal (during a rebuild).
    [[nodiscard]] core::Result<Placement> place(const RunRecord& run, const SectionRecord& section,
                                                const CaptureRecord& capture, bool tilted = false);

    /// The plane at `positionUm` tilted by the two angles, cut from the stack's volume as the
    /// stack's slices were (labels, geometry, template plane when the stack has them).
    /// \return InvalidArgument when no tilt search has read the volume, the errors of
    ///         cutStackPlane.
    [[nodiscard]] core::Result<pipeline::AtlasSlice> cutPlane(double positionUm, double tiltLrDeg,
                                                              double tiltDvDeg) const;

    /// The section's registration was journalled as `registrationId`, registered to
    /// `registeredSlice`: settle() will update it.
    void recorded(std::int64_t sectionId, std::int64_t registrationId, int registeredSlice);

    /// The section (of `runId`) failed: unless it is already in the model, its planned slot was
    /// not matched, and the gap it leaves before the next section is not a skip.
    void failed(std::int64_t runId, std::int64_t sectionId);

    /// A section whose word the model has confirmed.
    struct Settled {
        std::int64_t sectionId = 0;
        std::int64_t registrationId = 0; ///< 0 when its registration was not journalled
        SeriesPlacement series;
        int slice = 0;           ///< the stack slice nearest to series.positionUm
        int registeredSlice = 0; ///< the slice it was registered to (the word then)
        int matchedSlice = 0;
        /// The planned slice moved by the slots the model found skipped up to this section
        /// (signed spacing per slot), nearest stack slice: where the plan puts the section once
        /// the skips already reported are counted, so one skip is not an alert on every later
        /// section. Empty without a planned slice.
        std::optional<int> expectedSlice;
    };
    /// The sections of `runId` confirmed since the last call, each once: all but the newest, and
    /// the newest too when `runComplete` (it is the last of the plan). Empty for another run.
    std::vector<Settled> settle(std::int64_t runId, bool runComplete);

    /// The plan's interval for the model's prior: the median distance between consecutive
    /// planned positions (in plan order), 0 when fewer than two sections have one.
    static double planIntervalUm(const std::vector<SectionRecord>& sections,
                                 const AtlasStack& stack);
    /// The stack slice nearest to `positionUm` (slices are in position order).
    static int nearestSlice(const AtlasStack& stack, double positionUm);

private:
    struct Entry {
        std::int64_t sectionId = 0;
        std::size_t planIndex = 0;
        std::int64_t registrationId = 0;
        int registeredSlice = 0;
        int matchedSlice = 0;
        bool settled = false;
        pipeline::SectionFeatures features; ///< kept for finish() at the run's end
    };
    core::Result<void> reset(const RunRecord& run);
    core::Result<pipeline::SectionFeatures> featuresOf(const CaptureRecord& capture) const;
    core::Result<pipeline::SectionMatch> matchWhole(const pipeline::SectionFeatures& f) const;
    SeriesPlacement wordOn(std::size_t entry) const;
    std::string searchTiltIfDue();
    void applyTilt(Placement& out) const;
    bool tiltApplies() const;
    std::optional<int> expectedSlice(std::size_t entry) const;
    /// The plan's slice for the section at `planIndex` and its two neighbours (those in the
    /// stack), scored by the live match beside its shortlist; empty without a planned slice.
    std::vector<int> plannedSlices(std::size_t planIndex) const;
    void finishRun();
    /// The features of the model's sections, in the matcher's order (its matches' order).
    std::vector<pipeline::SectionFeatures> modelFeatures() const;

    Journal& journal_;
    const AtlasStack& stack_;
    const std::vector<pipeline::SliceFeatures>& slices_;
    std::filesystem::path stateDir_;
    std::int64_t runId_ = 0;
    std::vector<std::int64_t> planOrder_;        ///< the run's section ids in plan order
    std::vector<std::optional<int>> planSlices_; ///< their planned slices
    std::vector<bool> planFailed_; ///< failed before reaching the model (by plan index)
    bool finished_ = false;        ///< finish() has run for this run
    std::unique_ptr<pipeline::SeriesMatcher> matcher_;
    std::vector<Entry> entries_; ///< in the order added to the matcher

    std::optional<StackVolume> volume_; ///< read at the first tilt search, kept for the stack
    bool volumeRefused_ = false;        ///< this run cannot cut tilted planes (said once)
    int nextTiltAt_ = kTiltFirstSections;
    std::optional<pipeline::TiltEstimate> tilt_; ///< the run's latest tilt search
};

} // namespace slicestation::daemon
