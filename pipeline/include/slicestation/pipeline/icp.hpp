#pragma once
/// ICP affine with normals (paper section 3.2.3, "Global Alignment using ICP").

#include "slicestation/pipeline/edge_points.hpp"
#include "slicestation/pipeline/point_grid.hpp"

#include <opencv2/core.hpp>

#include <vector>

namespace slicestation::pipeline {

/// One tightening step: correspondences must lie within `distance` (target units) and their
/// normals within `angleDeg`.
struct IcpLevel {
    double angleDeg;
    double distance;
};

struct IcpOptions {
    std::vector<IcpLevel> levels;  ///< loosest first
    int maxIterationsPerLevel = 8; ///< stop a level earlier when the transform settles
    double settleDistance = 0.02;  ///< target units: largest point motion that counts as settled
    bool consistencyCheck = true;  ///< the paper's neighbourhood-consistency rejection
    int minMatches = 12;           ///< fewer matches leave the transform unchanged
};

/// How a match's target is formed from the target points in reach.
enum class TargetRule {
    WeightedAverage, ///< Eq. 1 of the paper: 1/d-weighted mean of all compatible points
    PointToLine,     ///< projection onto the tangent line of the nearest compatible point: moves
                     ///< only across the edge, where an edge says something (aperture problem)
};

/// A source point and where it should go in the target frame (Eq. 1).
struct Match {
    int source = -1;
    cv::Point2d target;
};

/// Target for each (already mapped) source point from the target points within `distance`
/// whose normal deviates less than `angleDeg` (by `rule`; Eq. 1 weights 1/d, 100 at d = 0),
/// then the neighbourhood-consistency check: a match whose displacement differs from the median
/// displacement of its neighbours by more than half the distance threshold is dropped
/// (neighbours within 2 * distance of the mapped point).
std::vector<Match> findMatches(const std::vector<cv::Point2f>& mappedPoints,
                               const std::vector<cv::Point2f>& mappedNormals,
                               const EdgePoints& target, const PointGrid& targetGrid,
                               double distance, double angleDeg, bool consistencyCheck,
                               TargetRule rule = TargetRule::WeightedAverage);

/// Least-squares affine taking source[m.source] to m.target (the paper's Z T = b system).
/// Returns false when the system is degenerate (then `out` is untouched).
bool fitAffine(const std::vector<cv::Point2f>& source, const std::vector<Match>& matches,
               cv::Matx23d& out);

struct IcpResult {
    cv::Matx23d targetFromSource;
    std::vector<Match> matches; ///< of the last iteration
    double rmsResidual = 0;     ///< target units, over `matches`
    int iterations = 0;
};

/// Iterates match / fit through the levels, starting from `init`.
IcpResult icpAffine(const EdgePoints& source, const EdgePoints& target, const PointGrid& targetGrid,
                    const cv::Matx23d& init, const IcpOptions& options);

} // namespace slicestation::pipeline
