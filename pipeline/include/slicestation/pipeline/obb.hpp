#pragma once
/// Oriented bounding boxes (paper section 3.2.1): PCA of the uniformly sampled convex hull, so
/// torn or missing tissue inside the outline does not bias the axes.

#include <opencv2/core.hpp>

#include <vector>

namespace slicestation::pipeline {

struct OrientedBox {
    cv::Point2d centre;
    cv::Vec2d major{1, 0}; ///< unit direction of the principal axis
    cv::Vec2d minor{0, 1}; ///< unit, perpendicular to major
    double halfMajor = 0;  ///< half extent along major
    double halfMinor = 0;  ///< half extent along minor
};

/// OBB of a point set: convex hull, `samples` points spread uniformly along the hull's perimeter,
/// PCA of those; extents from the hull. Needs at least 3 non-collinear points (else a degenerate
/// box with zero extents).
OrientedBox orientedBox(const std::vector<cv::Point2f>& points, int samples = 512);

} // namespace slicestation::pipeline
