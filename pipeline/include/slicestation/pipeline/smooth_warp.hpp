#pragma once
/// A smooth non-linear stage between the ICP affine and the Laplace warp (beyond the paper;
/// issue 17): non-rigid ICP with a cubic B-spline displacement on a coarse control grid.
///
/// The Laplace warp interpolates exact, local conditions: it reaches only edges the affine left
/// within a few atlas pixels and follows each condition wherever it lands. Sections are
/// deformed smoothly as a whole (shrinkage and swelling, compression along the cutting
/// direction, a stretched side) by more than that. This stage fits such a deformation with few
/// degrees of freedom (a control point every fifth of the section or so) to every edge and
/// outline correspondence at once: matches are found point-to-line as in the ICP, weighed
/// robustly, and a membrane term ties each control point to its neighbours, so far-off and
/// wrong matches move the field little and no single edge decides it.
///
/// Pure computation; no I/O, no threads, no logging.

#include "slicestation/pipeline/edge_points.hpp"
#include "slicestation/pipeline/laplace_warp.hpp"
#include "slicestation/pipeline/point_grid.hpp"

#include <opencv2/core.hpp>

#include <vector>

namespace slicestation::pipeline {

/// One point set to match and what it is matched against (target frame: atlas px).
struct SmoothWarpPairing {
    const EdgePoints* source = nullptr; ///< section points, working px
    const EdgePoints* target = nullptr; ///< atlas points
    const PointGrid* targetGrid = nullptr;
    double weight = 1.0; ///< weight of each of its matches
};

/// One tightening step of the matching.
struct SmoothWarpLevel {
    double distance; ///< atlas px: reach of a match
    double angleDeg; ///< normals must agree within this
    int iterations;
};

struct SmoothWarpOptions {
    /// Control point spacing (cubic B-spline) as a fraction of the domain's longer side.
    double nodeSpacing = 0.12;
    /// Membrane stiffness: weight of (neighbouring control points' difference)^2 per unit of
    /// match weight, relative to the number of matches per control point. Larger = stiffer.
    double stiffness = 0.01;
    /// Residuals beyond this many robust sigmas weigh under one half (Cauchy weights).
    double robustK = 2.0;
    std::vector<SmoothWarpLevel> levels; ///< loosest first; empty = no field
    int minMatches = 30;                 ///< fewer matches in an iteration leave the field as it is
    /// At each level the section points are thinned to one per cell of this fraction of the
    /// level's reach (atlas px; 0 = every point), as the ICP thins its levels (a point every
    /// reach / 8): a loose level is steered as well by fewer points, and its neighbour searches
    /// stay short.
    double thinning = 0.125;
};

struct SmoothWarp {
    /// Displacement (atlas px) added to the affine, sampled on nodes `cellPx` apart over the
    /// domain; empty when too few matches were found.
    DisplacementField field;
    int matches = 0;      ///< matches of the last iteration
    double rmsBefore = 0; ///< RMS point-to-line distance of the first iteration's matches
    double rmsAfter = 0;  ///< the same matches after the fit
};

/// Fits the smooth displacement d so that affine(p) + d(p) meets the targets, for points p of
/// a domain of `domain` working px. The result is sampled on nodes `cellPx` apart (the Laplace
/// warp's grid, so the two can be added).
SmoothWarp fitSmoothWarp(cv::Size domain, const cv::Matx23d& atlasFromWorking,
                         const std::vector<SmoothWarpPairing>& pairings, double cellPx,
                         const SmoothWarpOptions& options);

/// a + b on a's node grid (b sampled at a's nodes); either may be empty.
DisplacementField addFields(const DisplacementField& a, const DisplacementField& b);

} // namespace slicestation::pipeline
