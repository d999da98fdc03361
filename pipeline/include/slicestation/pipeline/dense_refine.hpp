#pragma once
/// Dense refinement of a section-to-atlas map, driven by the section's own contrast (beyond the
/// paper; issue 17). The geometric stages (edges, OBB, ICP, Laplace warp) give the start; this
/// step adds a smooth displacement so that the atlas regions fit what the section shows inside
/// the tissue.
///
/// The measure needs no intensity atlas: every atlas region is taken to have one unknown stain
/// level, so the section is predicted by the label image with each region painted at its mean
/// section intensity and blurred at the working scale (a label-conditional variance, i.e. the
/// correlation ratio between section intensity and atlas label). Optionally an atlas intensity
/// plane (e.g. the Allen average template) enters the prediction as a fitted linear term. The
/// field is found coarse to fine by damped Gauss-Newton steps solved in local windows (each step
/// is a local least-squares fit of the displacement), smoothed after each step, and every step
/// that would fold the map is shortened.
///
/// Pure computation; no I/O, no threads, no logging.

#include <opencv2/core.hpp>

#include <cstdint>
#include <utility>
#include <vector>

namespace slicestation::pipeline {

/// One coarse-to-fine level: lengths in refinement-grid pixels.
struct DenseLevel {
    double imageSigma; ///< Gaussian smoothing of the section and of the painted labels
    /// Half size of the window each displacement step is fitted in; with nodeGrid the control
    /// nodes are 2 x window apart.
    int window;
    int iterations;
};

struct DenseRefineOptions {
    int gridMaxSide = 256; ///< the refinement grid's longer side (the section is reduced to it)
    std::vector<DenseLevel> levels{{3.0, 18, 8}};
    double fieldSigma = 2.0; ///< grid px: smoothing of each step (fluid-like regularisation)
    /// grid px: the residual's weighted local mean at this scale is taken as an additive bias
    /// (uneven illumination, stain gradients) and removed; 0 = none.
    double biasSigma = 15.0;
    double elasticSigma = 0.0; ///< grid px: smoothing of the accumulated field after each step
    /// Each region's stain may vary linearly across it (a level and a gradient per region),
    /// rather than one level per region.
    bool regionGradients = true;
    /// Solve each step on a control grid of spacing 2 x the level's window (few degrees of
    /// freedom, interpolated bilinearly) rather than in a window round every grid pixel.
    bool nodeGrid = true;
    double damping = 0.1; ///< Levenberg damping, relative to the mean local gradient energy
    /// Prior on each step's displacement (atlas px): with the residual's noise it sets the
    /// damping, so that a step needs evidence above the texture and noise.
    double priorAtlasPx = 2.0;
    double maxStepGridPx = 0.25; ///< longest displacement change per step, grid px
    /// A step that would bring the local area ratio of the map (Jacobian determinant relative to
    /// the map's median over the tissue) below this, or that raises the energy, is halved, up to
    /// three times, then dropped.
    double minJacobian = 0.3;
    /// Residuals beyond this many robust sigmas weigh under one half (Cauchy weights); every
    /// step must lower the Cauchy energy.
    double robustK = 3.0;
    /// The refinement is kept only if it raises the explained share of the section's variance
    /// by at least this much (absolute).
    double minGain = 0.002;
    /// The field is fitted on a checkerboard of blocks this size (grid px) and the gain above is
    /// measured on the other blocks; 0 = fit and judge on all pixels.
    int holdOutBlockPx = 8;
    /// Confidence: a correction longer than this (grid px) halves the confidence.
    double confidenceCorrectionGridPx = 4.0;
};

struct DenseRefinement {
    cv::Mat ux, uy; ///< CV_32F, grid size: atlas px to add to the map; zero if not accepted
    /// CV_32F in [0,1], grid size: how far the atlas can be trusted locally (see registration.md);
    /// 0 outside the measured area.
    cv::Mat confidence;
    /// Share of the section's intensity variance (in the measured area) that the painted atlas
    /// explains, before and after the refinement (the correlation ratio, squared).
    double explainedBefore = 0, explainedAfter = 0;
    /// Smallest Jacobian determinant of the refined map relative to its median over the measured
    /// area (1 = no local change of area; <= 0 would be a fold).
    double minJacobian = 1;
    bool accepted = false;
    int regions = 0; ///< atlas regions seen in the measured area
};

/// Refines the map `mapX`, `mapY` (CV_32F, grid size: the atlas position of every grid pixel)
/// of the section `grey` (CV_32F, grid size, tissue bright) to the atlas `atlasLabels` (CV_32S).
/// `weight` (CV_8U, grid size, non-zero = counts) marks where the measure is taken: tissue and a
/// band of glass round it, without damage or excluded parts. `atlasIntensity` is empty or
/// CV_32F of the labels' size.
/// Preconditions (asserted; callers check outside input): sizes and types as stated.
DenseRefinement refineDense(const cv::Mat& grey, const cv::Mat& weight, const cv::Mat& mapX,
                            const cv::Mat& mapY, const cv::Mat& atlasLabels,
                            const cv::Mat& atlasIntensity, const DenseRefineOptions& options = {});

/// Mean of `confidence` (CV_32F) over each label of `labels` (CV_32S, same size) where `valid`
/// (CV_8U) is set, largest area first; label 0 left out.
std::vector<std::pair<std::int32_t, double>>
meanByLabel(const cv::Mat& confidence, const cv::Mat& labels, const cv::Mat& valid);

} // namespace slicestation::pipeline
