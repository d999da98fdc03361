#pragma once
/// Which slice of a pre-sliced atlas stack a section came from: a quick alignment of the section
/// to every slice (outline ICP from the OBB placement, paper section 3.2.1/3.2.3, at a coarse
/// working resolution), the tissue overlap as a first filter, then an edge ICP and a contour and
/// edge agreement score on a shortlist. Pure computation, re-entrant.
///
/// Features are computed once per stack (sliceFeatures) and once per section
/// (sectionFeatures), so matching one section against 132 slices takes a fraction of a second.

#include "slicestation/core/result.hpp"
#include "slicestation/pipeline/edge_points.hpp"
#include "slicestation/pipeline/obb.hpp"

#include <opencv2/core.hpp>

#include <functional>
#include <string>
#include <utility>
#include <vector>

namespace slicestation::pipeline {

/// One stack slice at the matching resolution.
struct SliceFeatures {
    double positionUm = 0;
    double workUmPerPx = 0; ///< pixel size of the working images below
    cv::Mat mask;           ///< CV_8U 255 inside the brain
    cv::Mat edgeDistance;   ///< CV_32F, px to the nearest label boundary (outer and inner)
    EdgePoints outline;     ///< outer contour, px
    EdgePoints edges;       ///< every label boundary, px
    cv::Mat regions;        ///< CV_16U, the slice's labels renumbered 1..regionCount (0 outside)
    int regionCount = 0;
    OrientedBox box;
    double areaPx = 0;
    double heightPx = 0; ///< brain extent along its minor axis (sets the ICP reach)
};

/// Features of one slice. `labels` CV_32S (0 outside) at `umPerPx`; the working pixel size is
/// `workUmPerPx` (use the same for every slice of a stack). An empty slice gives areaPx 0 and
/// is never matched.
SliceFeatures sliceFeatures(const cv::Mat& labels, double umPerPx, double positionUm,
                            double workUmPerPx);

/// A working pixel size that gives the largest brain of a stack about `targetPx` pixels across.
double matchWorkUmPerPx(const std::vector<cv::Mat>& labels, double umPerPx, int targetPx = 320);

struct SectionFeatures {
    double workUmPerPx = 0; ///< 0 when the section's pixel size is unknown
    double scale = 1;       ///< working px per full-resolution px
    cv::Mat grey;           ///< CV_32F working image (tissue bright)
    cv::Mat tissue;         ///< CV_8U 255, holes filled
    cv::Mat edgeDistance;   ///< CV_32F, px to the nearest dominant edge
    EdgePoints outline;
    EdgePoints edges;
    OrientedBox box;
    double areaPx = 0;
};

/// Prepares the section (prepareSection, dominant edges of Algorithm 1) at the working pixel
/// size when `imageUmPerPx` > 0, else at `unknownScaleMaxSide` px (the scale is then found per
/// slice from the areas).
/// \return the errors of prepareSection (InvalidArgument, NoTissue); NoTissue when too few edges.
[[nodiscard]] core::Result<SectionFeatures> sectionFeatures(const cv::Mat& image,
                                                            double imageUmPerPx, double workUmPerPx,
                                                            int unknownScaleMaxSide = 256);

struct MatchOptions {
    int first = 0;      ///< first slice index searched
    int last = -1;      ///< last slice index searched, -1 = the last slice
    int shortlist = 14; ///< slices, by tissue overlap, that get the edge alignment and score
    /// Slices scored beside the shortlist whatever their overlap (in [first, last]): those the
    /// cutting plan or the series model predicts, so that a section where the plan is right is
    /// never placed elsewhere for want of being scored (the whole-stack search on an atlas whose
    /// outline changes slowly may leave them off the overlap shortlist).
    std::vector<int> alsoScore;
    bool allowMirror = false; ///< also try mirrored placements (section mounted face down)
    /// Tilt is estimated from the positions the two halves of the section match best, when the
    /// stack is at most this far apart (micrometres); 0 disables it.
    double tiltMaxIntervalUm = 100;
    /// Called on the calling thread after each candidate alignment and each shortlist scoring:
    /// (candidates done, candidates in total). The total is every usable slice plus the
    /// shortlist, exact once the shortlist is chosen. For progress bars; may be empty.
    std::function<void(int done, int total)> progress;
};

struct MatchCandidate {
    int index = 0;
    double score = 0;             ///< 0..1, the product of the three agreements below
    double overlap = 0;           ///< tissue IoU after the alignment
    double edgeAgreement = 0;     ///< 0..1, two-way soft agreement of edges and slice boundaries
    double regionAgreement = 0;   ///< 0..1, how well the slice's regions explain the grey levels
    cv::Matx23d sliceFromSection; ///< working px -> slice working px
};

struct SectionMatch {
    int index = -1;        ///< best slice
    double positionUm = 0; ///< refined between neighbours (parabola through the scores)
    double score = 0;
    double tiltColumnsDeg = 0; ///< normal leaning toward the slice columns (coronal: LR)
    double tiltRowsDeg = 0;    ///< toward the rows (coronal: DV)
    bool tiltEstimated = false;
    std::vector<MatchCandidate> candidates;                ///< scored slices, best first
    std::vector<std::pair<std::string, double>> timingsMs; ///< step name -> milliseconds
};

/// Matches the section against slices [first, last]. Slices with no brain are skipped.
/// \return InvalidArgument (empty stack, bad range), NoTissue (nothing could be aligned).
[[nodiscard]] core::Result<SectionMatch> matchSection(const SectionFeatures& section,
                                                      const std::vector<SliceFeatures>& slices,
                                                      const MatchOptions& options = {});

/// Series mode: sections of one brain given in cutting order (front to back along the stack).
/// Each is matched on its own (matchSection over [first, last]), then one slice per section is
/// chosen so that the indices increase by at least `minStep` and the sum of the sections'
/// relative scores (score / that section's best score) is largest: a dynamic programme over
/// the per-section candidate scores. Each section is then matched again between the slices its
/// neighbours were given, so every slice it could still take is scored, and the programme runs
/// once more. The returned matches keep each section's own candidates and timings; `index`,
/// `score` and `positionUm` (refined by the neighbouring slices' scores, within half a slice so
/// the order holds) are the series' choice, and tilt is kept only where that choice is the
/// section's own best.
/// Not for single sections: it uses the order, which a lone section cannot know.
/// \return the errors of matchSection; InvalidArgument when the stack has fewer slices than the
///         series needs (sections x minStep).
struct SeriesOptions {
    MatchOptions match;
    int minStep = 1; ///< slices between consecutive sections, at least
};
[[nodiscard]] core::Result<std::vector<SectionMatch>>
matchSeries(const std::vector<SectionFeatures>& sections, const std::vector<SliceFeatures>& slices,
            const SeriesOptions& options = {});

} // namespace slicestation::pipeline
