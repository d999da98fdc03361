#pragma once
/// The series model: the sections of one brain, in the order they were cut, lie on a line
/// position = origin + spacing x slot, where a section's slot is its place in the cutting
/// sequence (section k has slot k unless sections were skipped, swapped or mounted out of
/// order), and the whole brain was cut at one angle. Fitted robustly from each section's own
/// matched position (a hypothesis per pair of nearby sections, then iteratively reweighted least
/// squares on the inliers), so a wrong match or a section out of order is an outlier of the
/// line, reported, instead of pulling the line. Pure computation, re-entrant.

#include "slicestation/core/result.hpp"

#include <string_view>
#include <vector>

namespace slicestation::pipeline {

/// One section's own match (from matchSection).
struct SeriesObservation {
    double positionUm = 0;
    double score = 1; ///< > 0; the fit weighs sections by it (relative to the series' median)
    double tiltColumnsDeg = 0;
    double tiltRowsDeg = 0;
    bool tiltEstimated = false;
};

struct SeriesModelOptions {
    /// The cutting plan's interval between consecutive sections, micrometres; 0 = unknown (the
    /// prior is then the Theil-Sen slope of position against index, from four sections on). It
    /// is a prior, not a constraint: the fitted spacing is the data's, but hypotheses further
    /// than `spacingSlack` from it are not tried.
    double intervalUm = 0;
    double spacingSlack = 0.35;
    /// A section further than this from its slot's position is off the line (an outlier);
    /// 0 = 0.4 x spacing.
    double inlierUm = 0;
    /// Order from the plan: a section whose own match breaks the cutting order (off the line,
    /// out of order, a duplicate) but scores under this fraction of the median score of the
    /// sections on the line is not believed: it is placed on the line at the free slot between
    /// its neighbours in the run (`Placed`). A match scoring at least this much stays an alert.
    /// 0 = never place.
    double placeScoreRatio = 0.5;
};

/// What the model says about one section.
enum class SeriesAnomaly {
    None,
    OffLine,    ///< its match lies between slots, far from the line: a wrong match or a stray
    Skipped,    ///< sections are missing just before this one (`missingBefore` slots)
    Swapped,    ///< exchanged with its neighbour
    OutOfOrder, ///< its slot breaks the cutting order (not a neighbour swap)
    Duplicate,  ///< the same slot as another section
    Placed,     ///< its own match broke the order with a weak score: placed on the line instead
};
std::string_view toString(SeriesAnomaly anomaly) noexcept;

struct SeriesSectionFit {
    int slot = 0; ///< place in the cutting sequence (section 0's slot is 0 in a clean run)
    double predictedUm = 0; ///< origin + spacing x slot
    double residualUm = 0;  ///< observed - predicted
    bool inlier = false;    ///< within inlierUm of its slot and in order
    SeriesAnomaly anomaly = SeriesAnomaly::None;
    int missingBefore = 0; ///< for Skipped: slots missing just before this section
    /// The series' answer for the section: its own match, or the line's position at its slot
    /// when `Placed`.
    double positionUm = 0;
};

struct SeriesFit {
    double originUm = 0;  ///< position of slot 0
    double spacingUm = 0; ///< between consecutive slots (signed: negative when cut back to front)
    double sigmaUm = 0;   ///< robust spread of the inliers' residuals (1.4826 x MAD)
    int inliers = 0;
    double tiltColumnsDeg = 0; ///< median of the inliers' tilt estimates
    double tiltRowsDeg = 0;
    int tiltSections = 0; ///< how many estimates the tilt comes from (0: no tilt)
    std::vector<SeriesSectionFit> sections;
    double positionOfSlot(double slot) const { return originUm + spacingUm * slot; }
    /// Where section `index` (0-based, in arrival order) should lie if the run continues
    /// regularly: its index plus the median slot offset (slot - index) of the last five on-line
    /// sections before it.
    double predictUm(int index) const;
};

/// Fits the series. One section gives a line through it with the plan's spacing.
/// \return InvalidArgument (no sections, a non-finite position or score, negative interval or
///         options out of range).
[[nodiscard]] core::Result<SeriesFit> fitSeries(const std::vector<SeriesObservation>& sections,
                                                const SeriesModelOptions& options = {});

} // namespace slicestation::pipeline
