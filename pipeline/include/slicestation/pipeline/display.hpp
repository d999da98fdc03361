#pragma once
/// Images made viewable: what the web page and the live view show.
/// Threading: pure functions, re-entrant.
#include <opencv2/core.hpp>

namespace slicestation::pipeline {

/// 8-bit for display: an 8-bit image is returned as is (shallow); deeper images are turned grey
/// (colour: luminance) and stretched linearly so the 0.5 and 99.5 percentiles of a sample of
/// every 7th pixel become 0 and 255. \return an empty Mat for an empty image.
cv::Mat displayStretch(const cv::Mat& image);

} // namespace slicestation::pipeline
