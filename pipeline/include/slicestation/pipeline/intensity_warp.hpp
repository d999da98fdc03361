#pragma once
/// Intensity-driven non-rigid refinement of a section-to-atlas map against an atlas intensity
/// plane (beyond the paper; issue 17). Where the section looks like the atlas's intensity image
/// (e.g. a plane of the Allen average template), a smooth displacement is added to the map so
/// that the section's grey image and the plane agree inside the tissue, as the intensity affine
/// does for the affine part (intensity_affine.hpp).
///
/// Field: cubic B-splines on control grids, coarse to fine (each level adds a B-spline field of
/// its own spacing to what the coarser levels found). Model: the section at grid pixel p is
/// gain(p) x T(map(p) + u(p)) + bias(p), with T the plane; gain and bias are either global
/// polynomials (gain quadratic, bias linear, as in the intensity affine) or local (a Gaussian
/// window's weighted linear regression, i.e. local normalised cross-correlation), refitted at
/// every step. Steps: damped Gauss-Newton on the control displacements with Cauchy weights and a
/// membrane term on the control points, each step at most maxStepGridPx, halved until the
/// penalised robust energy drops and the map's local area ratio stays above minJacobian (where
/// the start map is below it already, within foldSlack of the start's). The
/// field is fitted on a checkerboard of blocks and kept only if the share of the section's
/// variance the model explains on the other blocks rises by minGain; the field kept is then
/// fitted again on every pixel. Lattice and blocks start at the tissue's centroid.
///
/// Pure computation; no I/O, no threads, no logging.

#include <opencv2/core.hpp>

#include <cstdint>
#include <optional>
#include <vector>

namespace slicestation::pipeline {

/// One coarse-to-fine level; lengths in grid pixels.
struct IntensityWarpLevel {
    double imageSigma;    ///< Gaussian smoothing of the section (and, in atlas px, the plane)
    double spacingGridPx; ///< control point spacing of this level's B-spline
    int iterations;       ///< Gauss-Newton steps (at most)
};

struct IntensityWarpOptions {
    int gridMaxSide = 256; ///< the section is reduced to this longer side for the fit
    std::vector<IntensityWarpLevel> levels{{2.0, 48, 8}, {1.0, 24, 8}};
    /// Membrane weight on neighbouring control displacements, relative to the mean diagonal of
    /// the data term's normal equations over the control points that see data.
    double stiffness = 0.3;
    /// Levenberg damping relative to the same mean diagonal.
    double damping = 1e-3;
    double robustK = 3.0;       ///< Cauchy weights: beyond this many robust sigmas weigh < 1/2
    double maxStepGridPx = 1.0; ///< longest control displacement change per step, grid px
    /// A step that would bring the map's local area ratio (Jacobian determinant relative to its
    /// median over the measured area) below this is halved.
    double minJacobian = 0.3;
    /// Where the start map is already below minJacobian (a fold or squeeze the earlier stages
    /// left), a step may lower the ratio by at most this below the start's.
    double foldSlack = 0.1;
    /// Local gain and bias: Gaussian window (grid px) of the local regression; 0 = global
    /// polynomials.
    double localSigmaGridPx = 16;
    double minGain = 0.002; ///< held-out explained share must rise by at least this (absolute)
    int holdOutBlockPx = 8; ///< checkerboard block size (grid px); 0 = fit and judge on all
    /// Once the held-out blocks have judged the field worth keeping, the field kept is fitted
    /// again on every pixel of the measured area (off: the field of the fitting blocks is kept,
    /// half the pixels).
    bool refitOnAll = true;
    /// Where the control lattice and the checkerboard start (grid px). Unset: at the measured
    /// area's centroid, so that they move with the tissue and a section shifted in its frame
    /// gets the same field, shifted.
    std::optional<cv::Point2d> origin;
};

struct IntensityWarp {
    cv::Mat ux, uy; ///< CV_32F, grid size: atlas px to add to the map; zero if not kept
    /// Held-out explained share at the finest level, before and after the field fitted on the
    /// fitting blocks (the judgement; the field kept is then fitted on every pixel, refitOnAll).
    double explainedBefore = 0, explainedAfter = 0;
    /// Smallest Jacobian determinant of the map (with the field when kept) relative to its
    /// median over the measured area, over the whole grid (<= 0 would be a fold).
    double minJacobian = 1;
    bool accepted = false;
    int steps = 0; ///< Gauss-Newton steps taken
    /// The region warp: the regions left out of its fit (RegionWarpOptions::maxInnerSpread),
    /// ascending.
    std::vector<std::int32_t> leftOut;
};

/// Refines the map `mapX`, `mapY` (CV_32F, grid size: the atlas position of every grid pixel)
/// of `grey` (CV_32F, tissue bright) so that it agrees with `atlasIntensity` (CV_32F, atlas px)
/// where `weight` (CV_8U, grey's size) is set (tissue and a glass band, damage left out).
/// Preconditions (asserted): types and sizes as stated, every level's spacing >= 4 and sigma >= 0.
IntensityWarp refineWarpByIntensity(const cv::Mat& grey, const cv::Mat& weight, const cv::Mat& mapX,
                                    const cv::Mat& mapY, const cv::Mat& atlasIntensity,
                                    const IntensityWarpOptions& options = {});

/// The region warp: the same field fitted against a plane painted from the section itself, for
/// any stain (each atlas region is roughly homogeneous in any stain). Before each level, every
/// atlas region is painted with the median of the section's grey over the fitting blocks of the
/// measured area that the current map sends into it (regions seen on fewer than
/// `minRegionPx` grid px take the tissue's median; `glassIds`, e.g. ventricles, and the outside
/// take the glass band's median when `glassIds` are painted as glass); the level's field is then
/// fitted as by refineWarpByIntensity. It is kept only if the held-out explained share, each map
/// judged against its own painting, rises by `minGain`; the levels are then fitted again on every
/// pixel, each painted from all of them (IntensityWarpOptions::refitOnAll). Minimising the local
/// model's residual against such a painting is the within-region variance criterion with a local
/// gain and bias.
struct RegionWarpOptions {
    /// The field's levels, model and regularisation: the intensity warp's, with three levels
    /// (control points 64, 32, 16 grid px apart at sigmas 4, 2, 1; chosen on the second
    /// family's cases 0-23, docs/registration.md).
    IntensityWarpOptions warp = [] {
        IntensityWarpOptions o;
        o.levels = {{4.0, 64, 8}, {2.0, 32, 8}, {1.0, 16, 8}};
        return o;
    }();
    int minRegionPx = 8; ///< grid px a region needs to get its own level
    /// A region whose grey spreads inside (median absolute deviation over its interior, 2 grid
    /// px from its borders, under the start map) more than this many times the median of the
    /// regions' spreads is left out of the fit (0: none left out): one level describes a
    /// region stained evenly (its spread is the tissue's texture), not one with strong contrast
    /// inside it (the olfactory bulb's layers, a stain graded like the average template), whose
    /// inner contrast would otherwise be read as misplaced borders. Chosen on the second family's
    /// cases 0-95 and the template family's 0-47 (docs/registration.md).
    double maxInnerSpread = 2.0;
    bool glassLike = true; ///< paint `glassIds` at the glass band's level
    /// The ventricles' ids in RegistrationOptions::regionLabels.
    std::vector<std::int32_t> glassIds;
};

/// Refines the map as refineWarpByIntensity does, against planes painted from `grey` over
/// `atlasLabels` (CV_32S, atlas px) under the current map.
/// Preconditions (asserted): as refineWarpByIntensity; `atlasLabels` CV_32S and not empty.
IntensityWarp refineWarpByRegions(const cv::Mat& grey, const cv::Mat& weight, const cv::Mat& mapX,
                                  const cv::Mat& mapY, const cv::Mat& atlasLabels,
                                  const std::vector<std::int32_t>& glassIds,
                                  const RegionWarpOptions& options = {});

/// The plane refineWarpByRegions fits against (CV_32F, atlas size): `atlasLabels` painted with
/// the median of `grey` where `weight` (CV_32F or CV_8U, non-zero = counts) is set and the map
/// sends a grid pixel into the region. Exposed for tests.
cv::Mat paintRegions(const cv::Mat& grey, const cv::Mat& weight, const cv::Mat& mapX,
                     const cv::Mat& mapY, const cv::Mat& atlasLabels,
                     const std::vector<std::int32_t>& glassIds, const RegionWarpOptions& options);

} // namespace slicestation::pipeline
