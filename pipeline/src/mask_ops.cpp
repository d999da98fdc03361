#include "slicestation/pipeline/mask_ops.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>

namespace slicestation::pipeline {

cv::Mat fillHoles(const cv::Mat& mask) {
    std::vector<std::vector<cv::Point>> contours;
    cv::findContours(mask.clone(), contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_SIMPLE);
    cv::Mat filled = cv::Mat::zeros(mask.size(), CV_8U);
    cv::drawContours(filled, contours, -1, cv::Scalar(255), cv::FILLED);
    return filled;
}

std::vector<cv::Point2f> outerContourPoints(const cv::Mat& mask) {
    std::vector<std::vector<cv::Point>> contours;
    cv::findContours(mask.clone(), contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_NONE);
    std::vector<cv::Point2f> out;
    for (const auto& c : contours)
        for (const auto& p : c)
            out.emplace_back(float(p.x), float(p.y));
    return out;
}

float percentile(const cv::Mat& f32, double q, const cv::Mat& valid) {
    std::vector<float> v;
    v.reserve(f32.total());
    // A strided sample is plenty for a percentile and keeps this cheap on large images.
    const int step = std::max(1, static_cast<int>(std::sqrt(f32.total() / 250000.0)));
    for (int y = 0; y < f32.rows; y += step) {
        const float* row = f32.ptr<float>(y);
        const uchar* ok = valid.ptr<uchar>(y);
        for (int x = 0; x < f32.cols; x += step)
            if (ok[x])
                v.push_back(row[x]);
    }
    if (v.empty())
        return 0.0f;
    auto k = static_cast<size_t>(std::clamp(q, 0.0, 1.0) * static_cast<double>(v.size() - 1));
    std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(k), v.end());
    return v[k];
}

} // namespace slicestation::pipeline
