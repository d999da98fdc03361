#include "slicestation/pipeline/mask_ops.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>

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

float kthSmallest(std::vector<float>& values, size_t k) {
    CV_Assert(k < values.size());
    if (values.size() < 8192) {
        std::nth_element(values.begin(), values.begin() + static_cast<std::ptrdiff_t>(k),
                         values.end());
        return values[k];
    }
    // The float's bits made an unsigned key that sorts as the float does: its top 16 bits
    // pick the bucket holding the k-th value, and only that bucket is selected in.
    const auto key = [](float f) {
        std::uint32_t u;
        std::memcpy(&u, &f, sizeof u);
        return (u & 0x80000000u) ? ~u : (u | 0x80000000u);
    };
    std::vector<std::uint32_t> count(65536, 0);
    for (const float f : values)
        ++count[key(f) >> 16];
    size_t below = 0;
    std::uint32_t bucket = 0;
    while (below + count[bucket] <= k)
        below += count[bucket++];
    std::vector<float> inBucket;
    inBucket.reserve(count[bucket]);
    for (const float f : values)
        if ((key(f) >> 16) == bucket)
            inBucket.push_back(f);
    const size_t j = k - below;
    std::nth_element(inBucket.begin(), inBucket.begin() + static_cast<std::ptrdiff_t>(j),
                     inBucket.end());
    return inBucket[j];
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
    return kthSmallest(v, k);
}

} // namespace slicestation::pipeline
