#pragma once
/// Live series matching: sections of one brain arrive one at a time, in cutting order. The first
/// few are matched against the whole stack (matchSection); after that the series model
/// (series_model.hpp) predicts where the next one lies and only the slices around the
/// prediction are searched, from a little before (a swap) to two slots after (a skip). A window
/// whose best score falls well below the series' usual score is searched again over the whole
/// stack, so a section far out of order is still found. After each section the model is fitted
/// again. `finish` re-matches the sections that ended off the line near their predicted place.
/// Pure computation; one SeriesMatcher per run, not shared between threads.

#include "slicestation/core/result.hpp"
#include "slicestation/pipeline/atlas_matching.hpp"
#include "slicestation/pipeline/series_model.hpp"

#include <functional>
#include <vector>

namespace slicestation::pipeline {

struct SeriesMatchOptions {
    MatchOptions match;         ///< for every search (first/last bound the whole search)
    SeriesModelOptions model;   ///< intervalUm: the cutting plan's interval (0 = unknown)
    int fullSearchSections = 3; ///< sections matched against the whole stack first
    /// Search from this many spacings before the prediction (a swap puts the second section two
    /// slots before it) to this many after (a skip one slot after).
    double windowBeforeSpacings = 2.5;
    double windowAfterSpacings = 2.5;
    /// A windowed match scoring below this fraction of the series' median score is searched
    /// again over the whole stack, and the whole stack's answer kept only when it scores at
    /// least `fallbackGain` times the window's; 0 never.
    double fallbackScoreRatio = 0.5;
    double fallbackGain = 2.0;
    /// finish(): a flagged section moves to the slot that makes the run regular when it scores
    /// there at least this fraction of its own best (off-line sections move to any match on the
    /// line).
    double regularScoreRatio = 0.6;
    /// finish(), last: one candidate slice per section chosen for the whole series at once
    /// (a Viterbi pass over the sections' scored candidates): each section's relative score
    /// (candidate score / its best) less `orderWeight` x the squared deviation of each step
    /// from the fitted spacing, in spacings, capped at `orderCap` (a real skip costs one
    /// orderWeight, a swapped pair 6). 0 = not done.
    double orderWeight = 0.1;
    double orderCap = 4;
};

/// How one section was searched.
struct SeriesSearch {
    double predictedUm = 0; ///< the model's prediction before the match (0 when none)
    bool windowed = false;  ///< only the slices [first, last] were searched
    int first = 0, last = 0;
    bool fellBack = false; ///< the window's answer was weak and the whole stack was searched
    double ms = 0;         ///< matching time
};

/// Matching features of the plane at `positionUm` tilted by the two angles (degrees), cut from
/// the volume by the caller (atlas_slicing's sampleLabels, collapsed as the stack was) at the
/// stack's working pixel size.
using PlaneFeatures = std::function<core::Result<SliceFeatures>(
    double positionUm, double tiltColumnsDeg, double tiltRowsDeg)>;

/// How the tilt plane is searched.
enum class TiltSearchMethod {
    /// A cross of five tilts (the centre and one step either way on each angle); each angle's
    /// new centre is the vertex of the parabola through its three scores (or the best of them
    /// where the scores do not bend down), then the step is halved: coarseStepDeg, /2, ... down to
    /// fineStepDeg. About 5 tilts per step instead of a grid's (2n+1)^2.
    Cross,
    /// A grid within +-maxDeg at coarseStepDeg, then a grid at fineStepDeg within one coarse step
    /// of the best (the first version: 106 tilts with the defaults).
    Grid,
};

struct TiltSearchOptions {
    int sections = 6;           ///< the best-scoring on-line sections used
    double maxDeg = 4;          ///< tilts within +-maxDeg on both angles
    double coarseStepDeg = 2;   ///< first step (grid: the coarse grid's step)
    double fineStepDeg = 0.5;   ///< last step (grid: the fine grid's)
    double positionStepUm = 50; ///< planes at the section's position and this far either side
    TiltSearchMethod method = TiltSearchMethod::Cross;
    /// Cross: the answer is the vertex of a quadratic surface fitted to every tilt scored within
    /// three fineStepDeg of the last cross's vertex (when it bends down and moves the answer at
    /// most one fineStepDeg), else that vertex.
    bool surfaceFit = true;
};

struct TiltEstimate {
    double tiltColumnsDeg = 0;
    double tiltRowsDeg = 0;
    double score = 0; ///< summed best score of the sections at that tilt
    int sections = 0;
    int tiltsScored = 0; ///< distinct tilts whose planes were cut and matched
};

/// The brain's cutting angle from tilted planes: the sections on the series' line with the best
/// scores are matched against planes cut at their positions and each candidate tilt (see
/// TiltSearchMethod); the tilt whose planes the sections match best wins.
/// \return InvalidArgument (fewer than two on-line sections, bad options), the errors of
///         `planes`.
[[nodiscard]] core::Result<TiltEstimate>
searchSeriesTilt(const std::vector<SectionFeatures>& sections,
                 const std::vector<SectionMatch>& matches, const SeriesFit& fit,
                 const PlaneFeatures& planes, const TiltSearchOptions& options = {});

/// One place a section could take in the series: a position and how well the section matches
/// there relative to its own best (0..1).
struct SeriesOption {
    double positionUm = 0;
    double value = 0;
};

/// One option per section for the whole series at once (Viterbi): the largest sum of the chosen
/// options' values less `weight` x min(d^2, cap) per consecutive pair, d the pair's step in
/// units of `spacingUm` less one (a regular step costs 0, a skipped slot one weight, a swapped
/// pair 1 + 4 + 1 weights, anything further at most `cap` weights a step). Sections with no
/// option are not allowed (each needs at least its own match).
/// \return the chosen option's index per section; empty when `options` is, or a section has
///         none, or spacingUm is 0.
std::vector<size_t> chooseAlongSeries(const std::vector<std::vector<SeriesOption>>& options,
                                      double spacingUm, double weight, double cap);

class SeriesMatcher {
public:
    /// `slices` must outlive the matcher.
    SeriesMatcher(const std::vector<SliceFeatures>& slices, SeriesMatchOptions options);

    /// Matches the next section and refits the model; `alsoScore`: slices scored beside the
    /// search's shortlist (MatchOptions::alsoScore; the plan's slice for this section).
    /// \return the errors of matchSection (NoTissue...) and fitSeries; a failed section is not
    ///         added.
    [[nodiscard]] core::Result<SectionMatch> add(const SectionFeatures& section,
                                                 const std::vector<int>& alsoScore = {});

    /// Each flagged section (off the line, skip, swap, out of order, duplicate) is matched again
    /// around the slot that would make the run regular (after its on-line predecessor, before
    /// its successor; for a skip also the section before it one slot on) and moved there when
    /// it scores at least `regularScoreRatio` of its own match (off-line: any match on the
    /// line); the model is fitted again, twice at most. A real skip or swap stays: the regular
    /// place scores worse.
    /// \return the errors of fitSeries.
    [[nodiscard]] core::Result<void> finish(const std::vector<SectionFeatures>& sections);

    const std::vector<SectionMatch>& matches() const { return matches_; }
    const std::vector<SeriesSearch>& searches() const { return searches_; }
    const SeriesFit& fit() const { return fit_; }

private:
    core::Result<void> refit();
    bool reassign();
    int indexAt(double positionUm) const;

    const std::vector<SliceFeatures>* slices_;
    SeriesMatchOptions options_;
    std::vector<SectionMatch> matches_;
    std::vector<SeriesSearch> searches_;
    SeriesFit fit_;
};

} // namespace slicestation::pipeline
