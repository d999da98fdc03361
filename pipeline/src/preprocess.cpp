#include "slicestation/pipeline/preprocess.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <vector>

namespace slicestation::pipeline {
namespace {

using core::ErrorCode;
using core::makeError;

float percentile(const cv::Mat& f32, double q) {
    std::vector<float> v;
    v.reserve(f32.total());
    // A strided sample is plenty for a percentile and keeps this cheap on large images.
    const int step = std::max(1, static_cast<int>(std::sqrt(f32.total() / 250000.0)));
    for (int y = 0; y < f32.rows; y += step) {
        const float* row = f32.ptr<float>(y);
        for (int x = 0; x < f32.cols; x += step) v.push_back(row[x]);
    }
    auto k = static_cast<size_t>(std::clamp(q, 0.0, 1.0) * static_cast<double>(v.size() - 1));
    std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(k), v.end());
    return v[k];
}

/// Median of the outer ring of the image: the glass, on any sensibly framed capture.
float borderMedian(const cv::Mat& f32) {
    const int b = std::max(2, std::min(f32.rows, f32.cols) / 25);
    std::vector<float> v;
    for (int y = 0; y < f32.rows; ++y) {
        const float* row = f32.ptr<float>(y);
        const bool edgeRow = y < b || y >= f32.rows - b;
        for (int x = 0; x < f32.cols; ++x) {
            if (edgeRow || x < b || x >= f32.cols - b) v.push_back(row[x]);
        }
    }
    std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2), v.end());
    return v[v.size() / 2];
}

} // namespace

core::Result<cv::Mat> toGreyFloat(const cv::Mat& image) {
    if (image.empty()) return makeError(ErrorCode::InvalidArgument, "image is empty");
    const int depth = image.depth();
    if (depth != CV_8U && depth != CV_16U && depth != CV_32S && depth != CV_32F)
        return makeError(ErrorCode::InvalidArgument, "unsupported pixel type (depth " +
                                                         std::to_string(depth) + ")");
    cv::Mat one;
    switch (image.channels()) {
    case 1: one = image; break;
    case 2: cv::extractChannel(image, one, 0); break; // channel 0 carries the tissue stain
    case 3:
    case 4: {
        cv::Mat f;
        image.convertTo(f, CV_32F);
        cv::cvtColor(f, one, image.channels() == 3 ? cv::COLOR_BGR2GRAY : cv::COLOR_BGRA2GRAY);
        break;
    }
    default:
        return makeError(ErrorCode::InvalidArgument,
                         "unsupported channel count " + std::to_string(image.channels()));
    }
    cv::Mat out;
    one.convertTo(out, CV_32F);
    return out;
}

core::Result<PreparedSection> prepareSection(const cv::Mat& image, int workingMaxSide) {
    if (image.empty()) return makeError(ErrorCode::InvalidArgument, "image is empty");
    if (std::min(image.rows, image.cols) < 32)
        return makeError(ErrorCode::InvalidArgument,
                         "image is too small (" + std::to_string(image.cols) + "x" +
                             std::to_string(image.rows) + " px)");
    PreparedSection out;
    const int longSide = std::max(image.rows, image.cols);
    out.scale = longSide > workingMaxSide ? double(workingMaxSide) / longSide : 1.0;

    // Reduce first, in the stored type: converting a 40-megapixel frame to float would cost more
    // than the whole registration.
    cv::Mat small = image;
    if (out.scale < 1.0) {
        cv::Mat src = image;
        if (image.depth() == CV_32S) image.convertTo(src, CV_32F); // INTER_AREA lacks 32S
        cv::resize(src, small, cv::Size(), out.scale, out.scale, cv::INTER_AREA);
    }
    auto greyOr = toGreyFloat(small);
    if (!greyOr) return greyOr.error();
    cv::Mat grey = std::move(*greyOr);

    const float lo = percentile(grey, 0.005);
    const float hi = percentile(grey, 0.995);
    if (!(hi > lo)) return makeError(ErrorCode::NoTissue, "image is blank (no contrast)");
    grey = (grey - lo) / (hi - lo);
    cv::min(cv::max(grey, 0.0), 1.0, grey);

    // The glass is what surrounds the tissue: bright glass means brightfield, and we invert so
    // tissue is bright in both cases.
    const float glass = borderMedian(grey);
    out.contrast = glass > 0.5f ? Contrast::Brightfield : Contrast::Fluorescence;
    if (out.contrast == Contrast::Brightfield) grey = 1.0f - grey;
    out.grey = grey;

    // Tissue: smooth away cell texture, then Otsu between glass and tissue. Otsu on the full
    // histogram can split bright nuclei from dim tissue in fluorescence, so the threshold is
    // capped at a modest rise above the glass level.
    const double sigma = std::max(1.5, longSide * out.scale / 300.0);
    cv::Mat blurred;
    cv::GaussianBlur(grey, blurred, cv::Size(), sigma);
    cv::Mat u8;
    blurred.convertTo(u8, CV_8U, 255.0);
    cv::Mat mask;
    const double otsu = cv::threshold(u8, mask, 0, 255, cv::THRESH_BINARY | cv::THRESH_OTSU);
    const double glassLevel = 255.0 * (out.contrast == Contrast::Brightfield ? 1.0 - glass : glass);
    const double cap = glassLevel + 0.35 * (255.0 * percentile(blurred, 0.99) - glassLevel);
    cv::threshold(u8, mask, std::min(otsu, std::max(cap, glassLevel + 8.0)), 255,
                  cv::THRESH_BINARY);

    // Remove debris: keep components of at least 2% of the largest one.
    cv::Mat labels, stats, centroids;
    const int n = cv::connectedComponentsWithStats(mask, labels, stats, centroids, 8, CV_32S);
    int largest = 0;
    for (int i = 1; i < n; ++i) largest = std::max(largest, stats.at<int>(i, cv::CC_STAT_AREA));
    cv::Mat keep = cv::Mat::zeros(mask.size(), CV_8U);
    for (int i = 1; i < n; ++i) {
        if (stats.at<int>(i, cv::CC_STAT_AREA) >= std::max(16, largest / 50)) keep |= (labels == i);
    }
    const double share = cv::countNonZero(keep) / double(keep.total());
    if (share < 0.01)
        return makeError(ErrorCode::NoTissue, "no tissue found (tissue covers " +
                                                  std::to_string(share * 100) + "% of the image)");
    if (share > 0.97)
        return makeError(ErrorCode::NoTissue,
                         "no glass around the tissue: cannot tell tissue from background");
    // Pure noise also splits into "tissue" and "glass"; real tissue stands well clear of the
    // glass noise.
    cv::Scalar inMean, inSd, outMean, outSd;
    cv::meanStdDev(grey, inMean, inSd, keep);
    cv::meanStdDev(grey, outMean, outSd, ~keep);
    if (inMean[0] - outMean[0] < 1.0 * std::max(outSd[0], 1e-3))
        return makeError(ErrorCode::NoTissue,
                         "no tissue found (nothing stands out from the background)");
    out.tissueMask = keep;
    return out;
}

} // namespace slicestation::pipeline
