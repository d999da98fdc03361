#include "slicestation/pipeline/mask_ops.hpp"

#include <opencv2/imgproc.hpp>

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
        for (const auto& p : c) out.emplace_back(float(p.x), float(p.y));
    return out;
}

} // namespace slicestation::pipeline
