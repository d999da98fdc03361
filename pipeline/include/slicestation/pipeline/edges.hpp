#pragma once
/// Edge images: the atlas-edge image (AEI) from label boundaries and the microscope-edge image
/// (MEI) by the paper's dominant-edge detector (Algorithm 1, section 3.2.1).

#include <opencv2/core.hpp>

namespace slicestation::pipeline {

/// Parameters of Algorithm 1. Sizes are fractions of the image's longer side so the detector
/// behaves the same at every resolution; the paper's values (w_m = 20, w_g = 12, sigma_g = 2 at
/// 8000 px, s = 12, k = 5) are the defaults' origin.
struct DominantEdgeParams {
    double medianFrac = 0.01; ///< median window / long side (odd, at least 5 px)
    double sigmaFrac = 0.003; ///< Gaussian sigma / long side (at least 1 px)
    int stableBins = 5;       ///< k: consecutive histogram bins that must be stable
    /// s: allowed count change between adjacent bins, as a fraction of the histogram's peak
    /// count. The paper's absolute s = 12 belongs to its 40-megapixel images; relative to the
    /// peak the rule means the same at every size.
    double stableFraction = 0.01;
    double lowRatio = 0.5;      ///< hysteresis low threshold = lowRatio * K
    double minChainFrac = 0.01; ///< edge chains shorter than this * long side are dropped (specks)
};

/// Threshold K of Algorithm 1 from gradient magnitudes (any float Mat; zeros included).
/// Scott's rule bin width, the first k adjacent bins whose counts differ by at most s; K is the
/// mean magnitude of the values in those bins. Falls back to the 90th percentile when no stable
/// run exists (a degenerate histogram).
double dominantEdgeThreshold(const cv::Mat& gradientMagnitude, const DominantEdgeParams& params);

/// MEI: smooths (median, Gaussian), computes the Sobel gradient, K by dominantEdgeThreshold, and
/// thin edges by Canny hysteresis with K and lowRatio*K, then drops chains shorter than
/// minChainFrac of the long side (noise and cell texture). Input CV_32F in [0,1]; output CV_8U 255.
cv::Mat dominantEdges(const cv::Mat& grey, const DominantEdgeParams& params = {});

/// AEI: pixels whose label differs from the right or lower neighbour (outer and inner contours),
/// CV_8U 255. Input CV_32S labels, 0 outside the brain.
cv::Mat atlasEdges(const cv::Mat& labels);

} // namespace slicestation::pipeline
