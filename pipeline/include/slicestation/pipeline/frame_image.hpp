#pragma once
/// Camera frames as OpenCV images. Threading: pure function, re-entrant.
#include "slicestation/core/frame.hpp"

#include <opencv2/core.hpp>

namespace slicestation::pipeline {

/// A deep copy of the frame's pixels in OpenCV's conventions: Mono8 -> CV_8UC1, Mono16 ->
/// CV_16UC1, Rgb8 -> CV_8UC3 in BGR order. The Mat owns its pixels (safe to keep or hand to
/// another thread). An empty frame gives an empty Mat.
cv::Mat frameToMat(const hw::Frame& frame);

/// Sharpness of `image` (8/16-bit, 1 or 3 channels): mean squared Sobel gradient (Tenengrad)
/// of the grey image, computed on a copy downscaled to at most 512 px per side and divided by
/// the squared mean intensity, so exposure and gain do not change it. Higher is sharper;
/// comparable only between images of the same field. 0 for an empty or black image.

} // namespace slicestation::pipeline
