#pragma once
/// Edge points with normals, the features ICP matches (paper section 3.2.3: normals by moving
/// least squares).

#include <opencv2/core.hpp>

#include <vector>

namespace slicestation::pipeline {

struct EdgePoints {
    std::vector<cv::Point2f> points;  ///< pixel coordinates, pixel centres at integers
    std::vector<cv::Point2f> normals; ///< unit normals, sign arbitrary (edges are unoriented)
    size_t size() const { return points.size(); }
};

/// Moving-least-squares step on raw edge samples: for each kept sample, a Gaussian-weighted line
/// fit over the raw samples within `radius` gives the normal (smallest principal direction) and
/// the sample is projected onto that line, which removes pixel staircase and noise. Samples are
/// thinned to at most one per `spacing` x `spacing` cell; samples with fewer than 3 neighbours
/// are dropped (isolated specks carry no direction).
EdgePoints mlsEdgePoints(const std::vector<cv::Point2f>& raw, float spacing, float radius);

/// At most one point per `spacing` x `spacing` cell (the first met), normals kept.
EdgePoints thinEdgePoints(const EdgePoints& points, float spacing);

/// Edge pixels (non-zero) of an edge image as raw samples at the pixel centres.
std::vector<cv::Point2f> edgePixels(const cv::Mat& edgeImage);

/// Boundary samples of a label image at sub-pixel precision: the midpoint between every pair of
/// 4-neighbours whose labels differ (outer and inner contours).
std::vector<cv::Point2f> labelBoundarySamples(const cv::Mat& labels);

} // namespace slicestation::pipeline
