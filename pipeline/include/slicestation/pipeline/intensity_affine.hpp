#pragma once
/// Intensity-based refinement of the section-to-atlas affine against an atlas intensity plane
/// (beyond the paper; issue 17). When the section looks like the atlas's intensity image (e.g.
/// a plane of the Allen average template), the affine that the geometric stages found from
/// edges is polished so that the section's grey image and the plane agree over the tissue.
///
/// Model: the section at grid pixel p is gain(p) x T(A p) + bias(p), with T the plane, A the
/// affine, gain a quadratic and bias a linear polynomial in p (uneven illumination, vignetting),
/// fitted by least squares. A is found coarse to fine (both images smoothed at each level) by
/// damped Gauss-Newton steps on its six parameters with Cauchy weights, every step required to
/// lower the robust energy. The result is kept only if the share of the section's variance the
/// model explains rises on held-out blocks (fitted on a checkerboard of blocks, judged on the
/// others), as the dense refinement is judged.
///
/// Pure computation; no I/O, no threads, no logging.

#include <opencv2/core.hpp>

#include <vector>

namespace slicestation::pipeline {

struct IntensityAffineOptions {
    int gridMaxSide = 256; ///< the section is reduced to this longer side for the fit
    /// Coarse to fine: the Gaussian smoothing (grid px) of the section and (scaled to atlas px)
    /// of the plane at each level.
    std::vector<double> levelSigmas{4.0, 2.0, 1.0};
    int iterations = 12;  ///< Gauss-Newton steps per level (at most)
    double robustK = 3.0; ///< Cauchy weights: residuals beyond this many robust sigmas weigh < 1/2
    /// Levenberg damping relative to the mean diagonal of the normal equations.
    double damping = 1e-3;
    /// Longest move of any grid point per step, grid px.
    double maxStepGridPx = 1.0;
    /// The result is kept when the held-out explained share rises by at least this (absolute).
    double minGain = 0.002;
    int holdOutBlockPx = 8; ///< checkerboard block size (grid px); 0 = fit and judge on all
    /// The plane is a model of the section (a stain like the plane, seen through a smooth gain)
    /// only when it explains at least this share of the section's variance on the held-out
    /// blocks under the refined affine; below it nothing is kept, and registerSection sets the
    /// plane aside for its later stages. Measured (docs/registration.md, "When the plane is not
    /// the stain"): template-like sections 0.74-0.94, other stains at most 0.57.
    double minExplained = 0.65;
};

struct IntensityAffine {
    cv::Matx23d atlasFromGrid;                      ///< the refined affine (the start if not kept)
    double explainedBefore = 0, explainedAfter = 0; ///< held-out explained share, finest level
    /// explainedAfter reaches IntensityAffineOptions::minExplained: the plane is the stain.
    bool planeIsTheStain = false;
    bool accepted = false;
    int steps = 0; ///< Gauss-Newton steps taken
};

/// Refines `atlasFromGrid` (grid px -> atlas px) so that `grey` (CV_32F, tissue bright) agrees
/// with `atlasIntensity` (CV_32F, atlas px) where `weight` (CV_8U, grey's size) is set (tissue
/// and a glass band, damage left out). Preconditions (asserted): types and sizes as stated.
IntensityAffine refineAffineByIntensity(const cv::Mat& grey, const cv::Mat& weight,
                                        const cv::Matx23d& atlasFromGrid,
                                        const cv::Mat& atlasIntensity,
                                        const IntensityAffineOptions& options = {});

} // namespace slicestation::pipeline
