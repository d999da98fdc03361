#pragma once
/// Registration of one section image to its annotated atlas slice (paper section 3.2):
/// dominant edges, OBB initialisation, ICP affine with normals, Laplace warp.

#include "slicestation/core/result.hpp"
#include "slicestation/pipeline/damage.hpp"
#include "slicestation/pipeline/dense_refine.hpp"
#include "slicestation/pipeline/edge_points.hpp"
#include "slicestation/pipeline/edges.hpp"
#include "slicestation/pipeline/intensity_affine.hpp"
#include "slicestation/pipeline/intensity_warp.hpp"
#include "slicestation/pipeline/laplace_warp.hpp"
#include "slicestation/pipeline/preprocess.hpp"
#include "slicestation/pipeline/smooth_warp.hpp"

#include <opencv2/core.hpp>

#include <cstdint>
#include <functional>
#include <string>
#include <utility>
#include <vector>

namespace slicestation::pipeline {

/// The dense refinement's options with an atlas intensity plane: 24 steps of at most 0.5 grid
/// px, the rest as DenseRefineOptions.
inline DenseRefineOptions denseOptionsWithIntensity() {
    DenseRefineOptions o;
    o.levels = {{3.0, 18, 24}};
    o.maxStepGridPx = 0.5;
    return o;
}

struct RegistrationOptions {
    int workingMaxSide = 1024; ///< the section is reduced to this longer side for the work
    double imageUmPerPx = 0;   ///< section pixel size, 0 = unknown (scale is then found)
    double atlasUmPerPx = 0;   ///< atlas pixel size, 0 = unknown
    bool nonLinear = true;     ///< add the Laplace warp after the affine
    bool allowMirror = false;  ///< also try mirrored placements (section mounted face down)
    /// How far (degrees) a section may be turned on the slide relative to the atlas's
    /// orientation; 180 = any way. A lab that mounts every section dorsal side up sets e.g. 45:
    /// placements turned further are then not considered (unless none is within it).
    double maxTurnDeg = 180;
    /// Section pixels (full resolution, CV_8U, non-zero = exclude) whose edges must not take
    /// part in the matching, e.g. damaged tissue. Empty = none.
    cv::Mat excludeMask;
    DominantEdgeParams edges;
    /// When the section's tissue and the atlas brain overlap less than this (IoU) after the
    /// affine, the edges alone leave the outline misfit (a section cut far from the atlas plane's
    /// shape, parts shifted apart): the warp then also pairs the tissue outline with the atlas
    /// outline up to outlinePullReach x the atlas height away.
    double outlinePullBelowOverlap = 0.87;
    double outlinePullReach = 1.0 / 6;
    /// Where the final map folds (Jacobian determinant of the other sign than the affine's),
    /// relax the warp's nodes within 2 + r nodes of the fold (round r) to the harmonic
    /// interpolation of the nodes around them (relaxWithin), at most this many rounds; the field
    /// elsewhere is kept (0: keep the fold; docs/registration.md, "No folds").
    int foldRepairs = 3;
    /// After the geometric stages, refine the map densely so that the atlas regions fit the
    /// section's own contrast inside the tissue (dense_refine.hpp, docs/registration.md).
    bool denseRefine = true;
    DenseRefineOptions dense;
    /// A smooth B-spline field fitted to every edge and outline match before the Laplace warp
    /// (`smooth_warp.hpp`): deformations of the whole section beyond the Laplace warp's reach.
    /// Its matching levels are set from the atlas height in registerSection; these options set
    /// the spacing, stiffness and robustness (chosen on the second generator family's first 24
    /// cases). On by default since 2026-12-06 with damageWithoutSmooth: held out, the second
    /// family 2.9 -> 1.9 px (docs/registration.md, "The smooth warp on by default").
    bool smoothWarp = true;
    SmoothWarpOptions smooth;
    /// With the smooth warp, the damage check judges the section against the map the stages
    /// give without it (the two maps are computed side by side; the result keeps the smooth
    /// one): as flexible as chosen, the smooth map leaves larger gaps along clean real sections'
    /// natural notches, which the damage rules read as tears (docs/registration.md).
    bool damageWithoutSmooth = true;
    /// Optional atlas intensity plane (CV_32F, the size of the atlas labels, e.g. a plane of the
    /// Allen average template): it polishes the affine (intensityAffine) and is a second term of
    /// the dense refinement. Empty = none.
    cv::Mat atlasIntensity;
    /// With an atlas intensity plane: refine the ICP affine so that the section's grey image and
    /// the plane agree over the tissue (intensity_affine.hpp), kept only when it explains more of
    /// the section on held-out blocks. Parameters chosen on the template family's cases 0-23.
    bool intensityAffine = true;
    IntensityAffineOptions intensity;
    /// When the intensity affine is kept: still run the edge-driven warps (smooth warp, Laplace
    /// warp) after it. Off: the template stain's soft edges lie off the label boundaries, so the
    /// edges pull a well-placed atlas off again; the dense refinement (with the plane) then does
    /// the non-linear part alone.
    bool edgeWarpAfterIntensity = false;
    /// The dense refinement's options when an atlas intensity plane is given (in place of
    /// `dense`): the plane is strong evidence, so more and longer steps (24 of at most 0.5 grid
    /// px; chosen on the template family's cases 0-23, docs/registration.md).
    DenseRefineOptions denseWithIntensity = denseOptionsWithIntensity();
    /// With an atlas intensity plane: a smooth B-spline field fitted so that the section and the
    /// plane agree inside the tissue (intensity_warp.hpp), after the geometric stages and before
    /// the dense refinement; kept only when it explains more of the section on held-out blocks.
    bool intensityWarp = true;
    IntensityWarpOptions intensityWarpOptions;
    /// Without an atlas intensity plane (or with one set aside as not the section's stain,
    /// IntensityAffineOptions::minExplained) and with regionLabels (any stain): the same field
    /// fitted against the regions painted with the section's own median levels, re-painted before
    /// each level (refineWarpByRegions), after the geometric stages and before the dense
    /// refinement; kept only when it explains more of the section on held-out blocks.
    bool regionWarp = true;
    RegionWarpOptions regionWarpOptions;
    /// When the region warp runs (fine region labels, no atlas intensity plane): still run the
    /// edge-driven warps (smooth warp, Laplace warp) before it in the result's map. Off (since
    /// 2026-12-06): they match the section's edges, many of them borders between fine regions,
    /// to the major regions' edges and pull those borders off; the region warp and the dense
    /// refinement on the fine regions do the non-linear part (second family cases 0-95: 1.51 /
    /// 1.55 -> 0.94 / 1.02 px, docs/registration.md). The damage check still judges the map
    /// with the edge warps, the one its rules were made on.
    bool edgeWarpWithRegions = false;
    /// When the region warp runs without the edge warps in the result's map: the dense
    /// refinement after it still moves that map. Off (since 2026-12-06, fifth session): it only
    /// measures there (the confidence map; no step), because after the region warp, which fits
    /// the same fine regions with a local gain and a smooth field, its steps made no family
    /// better (family 2 cases 0-95 0.99 / 1.03 -> 0.99 / 1.01 px without them, family 1 the
    /// same, 1m 1.33 / 1.47 -> 1.28 / 1.45, template 0-47 3.13 / 3.17 -> 3.02 / 3.09;
    /// docs/registration.md). The damage check's map keeps the refinement.
    bool refineAfterRegionWarp = false;
    /// The labels the region warp paints (CV_32S, the atlas labels' size), e.g. every Allen id
    /// where the atlas labels are the collapsed major regions: a stain differs between fine
    /// regions, and a major region painted at one level is a poor model of the section (it made
    /// the second family worse, docs/registration.md). Empty: the region warp does not run.
    /// Their ventricles are regionWarpOptions.glassIds.
    cv::Mat regionLabels;
    bool detectDamage = true; ///< find damage and keep its edges out of the matching
    DamageParams damage;
    /// Atlas ids that are ventricles (empty like glass in a section): the major-region id 73.
    std::vector<std::int32_t> ventricleIds{73};
    /// Parts of the brain that lie apart across natural fissures which sectioning often opens,
    /// as groups of atlas (major-region) ids: the cerebral cortex (isocortex, olfactory areas,
    /// hippocampal formation, cortical subplate), the brain stem without the hypothalamus
    /// (thalamus, epithalamus, midbrain, pons, medulla; apart from the cortex across the
    /// transverse fissure) and the cerebellum (the tentorium, the fourth ventricle's recesses).
    /// The cerebral nuclei and the hypothalamus belong to none: they are joined to both sides.
    /// A gap with one part on one side and another on the other is not damage.
    std::vector<std::vector<std::int32_t>> separateParts{
        {315, 698, 1080, 822, 703}, {549, 958, 313, 771, 354}, {519, 528}};
    /// Called on the calling thread after each step (prepare, edges, ... damage) with the steps
    /// done and kRegistrationSteps; (total, total) when done. For progress bars; may be empty.
    std::function<void(int stepsDone, int stepsTotal)> progress;
};

/// The steps registerSection reports to RegistrationOptions::progress (steps skipped by the
/// options are counted as done when registration ends).
inline constexpr int kRegistrationSteps = 10;

struct RegistrationQuality {
    int correspondences = 0;         ///< tight correspondences that drive the warp
    double residualAffine = 0;       ///< RMS distance of those after the affine, atlas px
    double residualFinal = 0;        ///< RMS distance after affine + warp, atlas px
    double atlasBoundaryMatched = 0; ///< share of atlas boundary with a section edge nearby
    double sectionEdgesMatched = 0;  ///< share of section edge points with an atlas edge nearby
    double tissueOverlap = 0;        ///< IoU of the section's tissue and the mapped atlas brain
    double scaleAtlasPxPerImagePx = 0;
    /// Smallest Jacobian determinant of the final map (affine + warp) relative to the affine's,
    /// over the working domain: 1 = no local change of area, <= 0 = the map folds.
    double minJacobian = 1;
    /// Rounds of relaxWithin where the final map folded (RegistrationOptions::foldRepairs), and
    /// the warp nodes they relaxed in all.
    int foldRepairs = 0;
    int foldRepairNodes = 0;
    /// Share of the section's intensity variance (tissue and a glass band, damage left out)
    /// that the atlas regions, each painted at one fitted level, explain before and after the
    /// dense refinement (0 when it did not run).
    double explainedBeforeRefine = 0, explainedAfterRefine = 0;
    bool refined = false; ///< the dense refinement ran and was kept
    /// The intensity affine (with an atlas intensity plane): held-out share of the section's
    /// variance the plane explains under the ICP affine and under the refined one, and whether
    /// the refined one was kept (0, 0, false when it did not run).
    double intensityExplainedBefore = 0, intensityExplainedAfter = 0;
    bool intensityAffineKept = false;
    /// The atlas intensity plane was used past the intensity affine: it explains the stain
    /// (IntensityAffineOptions::minExplained). False without a plane, or when it was set aside
    /// (the later stages then run as without one).
    bool intensityPlaneUsed = false;
    /// The intensity warp: held-out explained share before and after, whether it was kept.
    double intensityWarpExplainedBefore = 0, intensityWarpExplainedAfter = 0;
    bool intensityWarpKept = false;
    /// The region warp: held-out explained share (each map against its own painting) before and
    /// after, whether it was kept.
    double regionWarpExplainedBefore = 0, regionWarpExplainedAfter = 0;
    bool regionWarpKept = false;
    /// The atlas ids the region warp left out of its fit (stained with strong contrast inside;
    /// RegionWarpOptions::maxInnerSpread), ascending; empty when it did not run.
    std::vector<std::int32_t> regionWarpLeftOut;
    /// The smooth stage: RMS point-to-line distance (atlas px) of its first matches before and
    /// after the fitted field, and how many matches its last iteration had (0 = not run).
    double smoothBefore = 0, smoothAfter = 0;
    int smoothMatches = 0;
};

/// The result: maps full-resolution section pixels to atlas pixels (pixel centres at integers,
/// origin top-left, x right, y down, in both images).
struct Registration {
    cv::Size imageSize;           ///< full-resolution section size
    double workingScale = 1.0;    ///< working px per full-resolution px
    cv::Matx23d atlasFromWorking; ///< the ICP affine, working px -> atlas px
    DisplacementField warp;       ///< atlas px, over the working image domain
    Contrast contrast = Contrast::Fluorescence;
    RegistrationQuality quality;
    std::vector<std::pair<std::string, double>> timingsMs; ///< step name -> milliseconds
    /// Step name -> process CPU milliseconds (all threads), the same steps as timingsMs: what
    /// a step costs on a loaded machine, where wall time also counts waiting. With more than one
    /// thread a step's figure includes work running beside it ("edges" runs beside
    /// "initialise" and carries its own thread's time).
    std::vector<std::pair<std::string, double>> cpuMs;
    cv::Mat workingGrey;       ///< CV_32F [0,1] tissue bright, working resolution
    cv::Mat workingTissueMask; ///< CV_8U, working resolution
    EdgePoints sectionEdges;   ///< working px, after exclusions
    EdgePoints atlasEdges;     ///< atlas px
    /// The affine (working px -> atlas px) after each stage: "obb", "outline", "icp"; for
    /// diagnosis and tests.
    std::vector<std::pair<std::string, cv::Matx23d>> stageAffines;
    /// How far the atlas can be trusted locally: CV_32F in [0,1] at working resolution, 0 off
    /// the measured tissue (see docs/registration.md, "Confidence"). Empty when the dense
    /// refinement is off.
    cv::Mat confidence;
    /// The mean confidence of each atlas region seen in the tissue (atlas id, confidence),
    /// largest region first.
    std::vector<std::pair<std::int32_t, double>> regionConfidence;

    bool damaged = false; ///< damageVerdict == Damaged
    /// The section's damage score in [0, 1] (damageScore); flagged at DamageParams::flagScore.
    double damageScore = 0;
    DamageVerdict damageVerdict = DamageVerdict::Clean;
    std::vector<DamageRegion> damage; ///< full-resolution pixels, largest first
    double damageFraction = 0;        ///< damaged area / tissue area
    double brainWidthPx = 0;          ///< the section's OBB major extent, full-resolution px
    std::string damageSummary;
    std::vector<Concavity> concavities; ///< deep outline concavities (working px), for diagnosis
    /// The glass the section shows inside its tissue (its closed holes) where the atlas expects
    /// tissue (beyond the registration slack): a ventricle wider than the atlas's, a tear.
    /// Outlines in atlas px through the map the damage was judged against: the series context
    /// counts a neighbour's such glass at the place of a band along a ventricle's lumen as
    /// anatomy carried through, whether or not that neighbour took it for a gap
    /// (damage_series.hpp, judgeInSeries).
    std::vector<std::vector<cv::Point2f>> glassAtlas;

    /// Working coordinates of a full-resolution pixel.
    cv::Point2d workingFromImage(cv::Point2d imagePx) const;
    /// Affine part only, full resolution -> atlas.
    cv::Matx23d affineAtlasFromImage() const;
    /// Affine then warp, full resolution -> atlas.
    cv::Point2d atlasFromImage(cv::Point2d imagePx) const;
    /// Atlas coordinates of every pixel of an image of `size` covering the section (full size
    /// or a reduced copy), CV_32F maps for cv::remap.
    void atlasMaps(cv::Size size, cv::Mat& mapX, cv::Mat& mapY) const;
    /// Atlas labels seen in the section frame at `size` (nearest neighbour), CV_32S.
    cv::Mat warpedLabels(const cv::Mat& atlasLabels, cv::Size size) const;
};

/// Registers `section` (any supported image, see prepareSection) to `atlasLabels` (CV_32S, 0
/// outside the brain). Returns a result whenever the inputs are valid, even for a poor match:
/// `quality` tells.
/// Threading: blocks the calling thread until done; independent parts run side by side on
/// OpenCV's threads (cv::setNumThreads; 1 runs everything on the caller), and the result is the
/// same to the bit with any number of them. Reentrant: calls from several threads share nothing.
/// \return InvalidArgument (empty or invalid atlas, bad options), NoTissue (see prepareSection).
[[nodiscard]] core::Result<Registration> registerSection(const cv::Mat& section,
                                                         const cv::Mat& atlasLabels,
                                                         const RegistrationOptions& options = {});

} // namespace slicestation::pipeline
