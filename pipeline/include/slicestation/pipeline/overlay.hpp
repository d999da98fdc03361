#pragma once
/// The picture a technician sees: the section with the atlas region outlines over it.

#include "slicestation/pipeline/registration.hpp"

#include <opencv2/core.hpp>

#include <vector>

namespace slicestation::pipeline {

/// Section rendered grey (tissue bright for fluorescence, as captured for brightfield) at `size`,
/// region outlines of `labelsInImage` (CV_32S, same size) drawn in colour, and optional damage
/// polygons (coordinates at `size`) filled translucent red. BGR 8-bit.
cv::Mat renderOverlay(const cv::Mat& sectionGrey, const cv::Mat& labelsInImage,
                      const std::vector<std::vector<cv::Point2f>>& damagePolygons = {});

/// The overlay of a registration at its working size: `atlasLabels` (the slice it was
/// registered to) warped into the section, its damage regions filled.
cv::Mat renderOverlay(const Registration& reg, const cv::Mat& atlasLabels);

} // namespace slicestation::pipeline
