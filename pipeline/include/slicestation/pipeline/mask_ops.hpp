#pragma once
/// Small operations on binary masks (CV_8U, non-zero = set) and on images weighted by one, shared
/// by the pipeline's steps.

#include <opencv2/core.hpp>

#include <vector>

namespace slicestation::pipeline {

/// The mask with every hole filled (outer contours drawn solid).
cv::Mat fillHoles(const cv::Mat& mask);

/// Every pixel of every outer contour, as points.
std::vector<cv::Point2f> outerContourPoints(const cv::Mat& mask);

/// The k-th smallest of `values` (k < size), the value std::nth_element puts at k (the order of
/// `values` changes); a histogram of the values' top bits first, so large sets cost two passes.
/// A -0 and a +0 compare equal and either may be returned.
float kthSmallest(std::vector<float>& values, size_t k);

/// The q-quantile (0..1) of the values of `f32` (CV_32F) where `valid` (CV_8U, same size) is
/// set, on a strided sample of about 250,000 pixels; 0 when none is set.
float percentile(const cv::Mat& f32, double q, const cv::Mat& valid);

/// What cv::connectedComponentsWithStats(mask, labels, stats, centroids, 8, CV_32S) gives for
/// labels and stats, computed from the mask's runs of set pixels (a union-find over runs), so
/// that it costs what the set pixels cost rather than the whole image. The components are
/// numbered as OpenCV's block-based labelling numbers them: by the first 2 x 2 block (block row,
/// then block column) holding one of their pixels. Row 0 of `stats` (the background) carries its
/// area; its box is the whole mask. Returns the number of labels (components + 1).
int labelComponents(const cv::Mat& mask, cv::Mat& labels, cv::Mat& stats);

/// The local mean of `values` (CV_32F) weighted by `weight` (CV_32F, 0..1, same size): a
/// Gaussian of `sigma` px over values times weight, divided by the same Gaussian over the weight
/// (plus 1e-6), borders replicated. The mean is smooth, so it is taken on a copy reduced `factor`
/// times (an integer, at least 1; the size rounded up) and brought back (bilinear). About 0 where
/// no weight lies within reach.
cv::Mat weightedLocalMean(const cv::Mat& values, const cv::Mat& weight, double sigma, int factor);

} // namespace slicestation::pipeline
