#include "slicestation/pipeline/focus_measures.hpp"

#include "slicestation/pipeline/mask_ops.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>

namespace slicestation::pipeline {
namespace {

/// Grey float image scaled so that full scale is 1, downscaled (area average) to at most
/// `maxSide` pixels per side.
cv::Mat normalisedGrey(const cv::Mat& image, int maxSide) {
    cv::Mat grey;
    if (image.channels() == 3) {
        cv::cvtColor(image, grey, cv::COLOR_BGR2GRAY);
    } else if (image.channels() == 4) {
        cv::cvtColor(image, grey, cv::COLOR_BGRA2GRAY);
    } else {
        grey = image;
    }
    const double fullScale = grey.depth() == CV_16U ? 65535.0 : grey.depth() == CV_8U ? 255.0 : 1.0;
    cv::Mat f;
    grey.convertTo(f, CV_32F, 1.0 / fullScale);
    const int longest = std::max(f.cols, f.rows);
    if (longest > maxSide) {
        const double k = static_cast<double>(maxSide) / longest;
        cv::resize(f, f, cv::Size(), k, k, cv::INTER_AREA);
    }
    return f;
}

/// The p-quantile of every pixel (mask_ops' percentile samples every pixel of images this
/// small: at most 512 x 512).
float quantile(const cv::Mat& f, double p) {
    return percentile(f, p, cv::Mat(f.size(), CV_8U, cv::Scalar(255)));
}

} // namespace

double focusMeasure(const cv::Mat& image) {
    if (image.empty())
        return 0;
    try {
        const cv::Mat f = normalisedGrey(image, 512);
        const double mean = cv::mean(f)[0];
        if (!(mean > 1e-6))
            return 0;
        cv::Mat gx;
        cv::Mat gy;
        cv::Sobel(f, gx, CV_32F, 1, 0, 3);
        cv::Sobel(f, gy, CV_32F, 0, 1, 3);
        // Tenengrad (Tenenbaum 1970; among the most robust measures in the comparisons of
        // Groen, Young & Ligthart 1985 and Krotkov 1987), normalised by the squared mean.
        const double tenengrad = cv::mean(gx.mul(gx) + gy.mul(gy))[0];
        return tenengrad / (mean * mean);
    } catch (const cv::Exception&) {
        return 0;
    }
}

double tissueFraction(const cv::Mat& image) {
    if (image.empty())
        return 0;
    try {
        const cv::Mat f = normalisedGrey(image, 256);
        if (f.total() < 4)
            return 0;
        const float median = quantile(f, 0.5);
        const bool brightField = median > 0.5F;
        const float glass = quantile(f, brightField ? 0.98 : 0.02);
        // Noise from horizontal neighbour differences: for white noise d = n1 - n2 has
        // sigma * sqrt(2); the median absolute value of a normal is 0.6745 sigma.
        cv::Mat d = cv::abs(f.colRange(1, f.cols) - f.colRange(0, f.cols - 1));
        const double noise = d.empty() ? 0 : quantile(d, 0.5) / 0.6745 / std::sqrt(2.0);
        const double threshold = std::max(5 * noise, 0.02);
        cv::Mat tissue = brightField ? (f < glass - threshold) : (f > glass + threshold);
        return static_cast<double>(cv::countNonZero(tissue)) / static_cast<double>(f.total());
    } catch (const cv::Exception&) {
        return 0;
    }
}

} // namespace slicestation::pipeline
