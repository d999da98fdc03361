#include "slicestation/pipeline/display.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <vector>

namespace slicestation::pipeline {

cv::Mat displayStretch(const cv::Mat& m) {
    if (m.empty())
        return cv::Mat();
    if (m.depth() == CV_8U)
        return m;
    cv::Mat grey = m.channels() == 1 ? m : cv::Mat();
    if (grey.empty())
        cv::cvtColor(m, grey, m.channels() == 4 ? cv::COLOR_BGRA2GRAY : cv::COLOR_BGR2GRAY);
    cv::Mat f;
    grey.convertTo(f, CV_32F);
    if (!f.isContinuous())
        f = f.clone();
    std::vector<float> sample;
    sample.reserve(f.total() / 7 + 1);
    for (std::size_t i = 0; i < f.total(); i += 7)
        sample.push_back(f.at<float>(static_cast<int>(i)));
    auto at = [&](double q) {
        auto it = sample.begin() +
                  static_cast<std::ptrdiff_t>(q * static_cast<double>(sample.size() - 1));
        std::nth_element(sample.begin(), it, sample.end());
        return static_cast<double>(*it);
    };
    const double lo = at(0.005), hi = std::max(at(0.995), lo + 1);
    cv::Mat out;
    f.convertTo(out, CV_8U, 255.0 / (hi - lo), -lo * 255.0 / (hi - lo));
    return out;
}

} // namespace slicestation::pipeline
