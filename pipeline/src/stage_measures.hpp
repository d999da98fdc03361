#pragma once
/// What the dense and intensity stages measure alike (private to the pipeline's sources): weighted
/// means, the held-out split of the measured pixels, and a map's Jacobian determinant.

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <cmath>

namespace slicestation::pipeline {

/// Weighted mean of `v` (CV_32F) with weights `w` (CV_32F); 0 when the weights sum to 0.
inline double weightedMean(const cv::Mat& v, const cv::Mat& w) {
    const double sw = cv::sum(w)[0];
    return sw > 0 ? v.dot(w) / sw : 0.0;
}

/// The centroid of a weight's set pixels (the image's centre when none is): a point that moves
/// with the tissue, where the fits' lattices and checkerboards start.
inline cv::Point2d weightCentroid(const cv::Mat& weight) {
    const cv::Moments m = cv::moments(weight, true);
    if (m.m00 <= 0)
        return {weight.cols / 2.0, weight.rows / 2.0};
    return {m.m10 / m.m00, m.m01 / m.m00};
}

/// Whether pixel (x, y) lies in a held-out block of the checkerboard of `blockPx` starting at
/// `origin`.
inline bool heldOutBlock(int x, int y, int blockPx, cv::Point2d origin) {
    const auto bx = static_cast<long>(std::floor((x - origin.x) / blockPx));
    const auto by = static_cast<long>(std::floor((y - origin.y) / blockPx));
    return ((bx + by) % 2 + 2) % 2 == 1;
}

/// The weights `w` (CV_32F) split for a held-out measure: `train` keeps the blocks of
/// `blockPx` (starting at `origin`) whose (column block + row block) is even, `test` the
/// others, so that a model is fitted on half the pixels and judged on the other half.
/// `blockPx` <= 0: both are `w`.
struct HeldOutWeights {
    cv::Mat train, test;
};
inline HeldOutWeights heldOutWeights(const cv::Mat& w, int blockPx, cv::Point2d origin = {0, 0}) {
    HeldOutWeights h{w.clone(), w.clone()};
    if (blockPx > 0)
        for (int y = 0; y < w.rows; ++y) {
            float* a = h.train.ptr<float>(y);
            float* b = h.test.ptr<float>(y);
            for (int x = 0; x < w.cols; ++x)
                (heldOutBlock(x, y, blockPx, origin) ? a : b)[x] = 0;
        }
    return h;
}

/// Local area ratio of a map (atlas px^2 per grid px^2): the Jacobian determinant of (ax, ay)
/// (CV_32F) by central differences.
inline cv::Mat jacobianDet(const cv::Mat& ax, const cv::Mat& ay) {
    cv::Mat xx, xy, yx, yy;
    cv::Sobel(ax, xx, CV_32F, 1, 0, 1, 0.5, 0, cv::BORDER_REPLICATE);
    cv::Sobel(ax, xy, CV_32F, 0, 1, 1, 0.5, 0, cv::BORDER_REPLICATE);
    cv::Sobel(ay, yx, CV_32F, 1, 0, 1, 0.5, 0, cv::BORDER_REPLICATE);
    cv::Sobel(ay, yy, CV_32F, 0, 1, 1, 0.5, 0, cv::BORDER_REPLICATE);
    return xx.mul(yy) - xy.mul(yx);
}

} // namespace slicestation::pipeline
