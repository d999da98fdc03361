#include "slicestation/pipeline/preprocess.hpp"

#include "side_by_side.hpp"
#include "slicestation/pipeline/mask_ops.hpp"

#include <Eigen/Dense>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <array>
#include <cmath>
#include <vector>

namespace slicestation::pipeline {
namespace {

using core::ErrorCode;
using core::makeError;

/// Calls `f(y, x)` for every valid pixel of the ring along the border of the valid area's
/// bounding box (a band of 1/25 of its shorter side, at least 2 px), row by row: the pixels where
/// a sensibly framed capture shows the glass.
template <typename F> void forEachRingPixel(const cv::Mat& valid, F&& f) {
    const cv::Rect box = cv::boundingRect(valid);
    const int b = std::max(2, std::min(box.width, box.height) / 25);
    for (int y = box.y; y < box.y + box.height; ++y) {
        const uchar* ok = valid.ptr<uchar>(y);
        const bool edgeRow = y < box.y + b || y >= box.y + box.height - b;
        const auto visit = [&](int x0, int x1) {
            for (int x = x0; x < x1; ++x)
                if (ok[x])
                    f(y, x);
        };
        if (edgeRow) {
            visit(box.x, box.x + box.width);
        } else { // the band's left and right parts only (they may meet in a narrow box)
            const int left = std::min(box.x + b, box.x + box.width);
            visit(box.x, left);
            visit(std::max(left, box.x + box.width - b), box.x + box.width);
        }
    }
}

/// Median of the valid pixels nearest the image border: the glass, on any sensibly framed
/// capture. The ring is found on the valid area's bounding box so zero padding is skipped.
float borderMedian(const cv::Mat& f32, const cv::Mat& valid) {
    std::vector<float> v;
    forEachRingPixel(valid, [&](int y, int x) { v.push_back(f32.at<float>(y, x)); });
    if (v.empty())
        return 0.0f;
    std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2), v.end());
    return v[v.size() / 2];
}

/// Robust spread (1.4826 x median absolute deviation from `glass`) of `image` over the valid
/// border ring: the glass noise at that blur.
float ringDeviation(const cv::Mat& image, const cv::Mat& valid, float glass) {
    std::vector<float> ring;
    forEachRingPixel(
        valid, [&](int y, int x) { ring.push_back(std::abs(image.at<float>(y, x) - glass)); });
    if (ring.empty())
        return 0.01f;
    std::nth_element(ring.begin(), ring.begin() + static_cast<std::ptrdiff_t>(ring.size() / 2),
                     ring.end());
    return std::max(0.002f, 1.4826f * ring[ring.size() / 2]);
}

/// Tissue in a normalised, tissue-bright working image, in two passes. A heavy blur averages
/// cell texture so that even dim tissue stands above the glass noise: that finds where tissue
/// is. Then the outline is placed half way between the glass and the dimmest tissue on a lightly
/// blurred copy, so it sits on the real edge instead of a blur radius outside it.
/// `fine`, when given, receives the mask before the closing.
cv::Mat segmentTissue(const cv::Mat& grey, const cv::Mat& valid, float glass,
                      cv::Mat* fine = nullptr) {
    const int longSide = std::max(grey.rows, grey.cols);
    // The three blurs side by side (the sharp one only for the fine mask).
    cv::Mat heavy, light, sharp;
    runTasks(fine ? 3 : 2, [&](int k) {
        if (k == 0)
            cv::GaussianBlur(grey, heavy, cv::Size(), std::max(2.0, longSide / 150.0));
        else if (k == 1)
            cv::GaussianBlur(grey, light, cv::Size(), std::max(1.0, longSide / 500.0));
        else
            cv::GaussianBlur(grey, sharp, cv::Size(), 1.0);
    });

    const float mad = ringDeviation(heavy, valid, glass);
    const float madLight = ringDeviation(light, valid, glass);
    // Uneven illumination also spreads the ring's values, so the noise margin is capped at a
    // fraction of the tissue's contrast.
    const float bright = percentile(heavy, 0.9, valid);
    const float margin =
        std::max(0.03f, std::min(6.0f * std::max(mad, 0.01f), 0.3f * (bright - glass)));
    cv::Mat coarse = (heavy > glass + margin) & valid;
    if (cv::countNonZero(coarse) == 0)
        return coarse;

    // The dimmest tissue: a low percentile of the heavy blur inside the coarse region, away
    // from its blurred rim.
    cv::Mat inner;
    cv::erode(coarse, inner, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(9, 9)),
              cv::Point(-1, -1), std::max(1, longSide / 150));
    if (cv::countNonZero(inner) < 64)
        inner = coarse;
    const float dim = percentile(heavy, 0.05, inner);
    // The outline sits half way between the glass and the dimmest tissue, where a blurred edge
    // really is. Inside that outline, anything clearly above the glass noise is tissue too: dark
    // tissue (white matter has few nuclei) is not glass.
    const float outlineT = glass + std::max(0.5f * (dim - glass), 0.5f * margin);
    const float clearlyAbove = std::max(0.1f * (bright - glass), 8.0f * madLight);
    const float insideT =
        glass + std::max(0.5f * margin, std::min(0.5f * (dim - glass), clearlyAbove));
    const int r = std::max(1, longSide / 250);
    const cv::Mat disc =
        cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * r + 1, 2 * r + 1));
    cv::Mat reach;
    cv::dilate(coarse, reach, disc);
    const cv::Mat outline = (light > outlineT) & valid & reach;
    const cv::Mat inside = fillHoles(outline);
    cv::Mat mask = outline | ((light > insideT) & inside);
    if (fine) {
        // For damage: everything clearly above the glass is tissue, also dark tissue at the
        // outline (the outline's exact place does not matter there), and thin cracks survive
        // only the lightest blur.
        *fine = (sharp > insideT) & valid & reach;
    }
    // Close the gaps between cells in dim, textured tissue.
    cv::morphologyEx(mask, mask, cv::MORPH_CLOSE, disc);
    return mask & reach;
}

/// Fits a quadratic surface to the glass (valid pixels well away from `tissue`) and subtracts
/// it, keeping the glass at `glassLevel`, from `grey` (clipped to [0,1] again) and from its
/// unclipped twin `level` (left unclipped). Returns false (images untouched) when too little
/// glass is seen for a fit.
bool flattenBackground(cv::Mat& grey, const cv::Mat& valid, const cv::Mat& tissue, float glassLevel,
                       cv::Mat& level) {
    const int longSide = std::max(grey.rows, grey.cols);
    cv::Mat away;
    cv::dilate(tissue, away, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(5, 5)),
               cv::Point(-1, -1), std::max(1, longSide / 100));
    const cv::Mat glassMask = valid & ~away;
    const int step = std::max(1, longSide / 256);
    Eigen::Matrix<double, 6, 6> ata = Eigen::Matrix<double, 6, 6>::Zero();
    Eigen::Matrix<double, 6, 1> atb = Eigen::Matrix<double, 6, 1>::Zero();
    int n = 0;
    const double sx = 2.0 / grey.cols, sy = 2.0 / grey.rows; // coordinates in [-1, 1]
    for (int y = 0; y < grey.rows; y += step)
        for (int x = 0; x < grey.cols; x += step) {
            if (!glassMask.at<uchar>(y, x))
                continue;
            const double u = x * sx - 1, v = y * sy - 1;
            Eigen::Matrix<double, 6, 1> r;
            r << 1, u, v, u * u, u * v, v * v;
            ata += r * r.transpose();
            atb += r * grey.at<float>(y, x);
            ++n;
        }
    if (n < 200)
        return false;
    const Eigen::Matrix<double, 6, 1> c = ata.ldlt().solve(atb);
    if (!c.allFinite())
        return false;
    for (int y = 0; y < grey.rows; ++y) {
        float* row = grey.ptr<float>(y);
        float* unclipped = level.ptr<float>(y);
        const double v = y * sy - 1;
        for (int x = 0; x < grey.cols; ++x) {
            const double u = x * sx - 1;
            const double bg =
                c[0] + c[1] * u + c[2] * v + c[3] * u * u + c[4] * u * v + c[5] * v * v;
            row[x] = std::clamp(float(row[x] - bg + glassLevel), 0.0f, 1.0f);
            unclipped[x] = float(unclipped[x] - bg + glassLevel);
        }
    }
    return true;
}

} // namespace

core::Result<cv::Mat> toGreyFloat(const cv::Mat& image) {
    if (image.empty())
        return makeError(ErrorCode::InvalidArgument, "image is empty");
    const int depth = image.depth();
    if (depth != CV_8U && depth != CV_16U && depth != CV_32S && depth != CV_32F)
        return makeError(ErrorCode::InvalidArgument,
                         "unsupported pixel type (depth " + std::to_string(depth) + ")");
    cv::Mat one;
    switch (image.channels()) {
    case 1:
        one = image;
        break;
    case 2:
        cv::extractChannel(image, one, 0);
        break; // channel 0 carries the tissue stain
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
    if (image.empty())
        return makeError(ErrorCode::InvalidArgument, "image is empty");
    if (std::min(image.rows, image.cols) < 32)
        return makeError(ErrorCode::InvalidArgument, "image is too small (" +
                                                         std::to_string(image.cols) + "x" +
                                                         std::to_string(image.rows) + " px)");
    PreparedSection out;
    const int longSide = std::max(image.rows, image.cols);
    out.scale = longSide > workingMaxSide ? double(workingMaxSide) / longSide : 1.0;

    // Reduce first, in the stored type: converting a 40-megapixel frame to float would cost more
    // than the whole registration.
    cv::Mat small = image;
    if (out.scale < 1.0) {
        cv::Mat src = image;
        if (image.depth() == CV_32S)
            image.convertTo(src, CV_32F); // INTER_AREA lacks 32S
        cv::resize(src, small, cv::Size(), out.scale, out.scale, cv::INTER_AREA);
    }
    auto greyOr = toGreyFloat(small);
    if (!greyOr)
        return greyOr.error();
    cv::Mat grey = std::move(*greyOr);

    // Scanners and stitchers pad the acquired area with exact zeros (or the minimum); such
    // "no data" pixels are neither glass nor tissue and must not steer the statistics.
    double rawMin = 0;
    cv::minMaxLoc(grey, &rawMin, nullptr);
    cv::Mat valid = grey != rawMin;
    if (cv::countNonZero(valid) > 0.99 * double(grey.total()) || cv::countNonZero(valid) < 64)
        valid.setTo(255);

    const float lo = percentile(grey, 0.005, valid);
    const float hi = percentile(grey, 0.995, valid);
    if (!(hi > lo))
        return makeError(ErrorCode::NoTissue, "no tissue found: the image is blank (no contrast)");
    grey = (grey - lo) / (hi - lo);
    cv::Mat level = grey.clone(); // the same scale, not clipped at the percentiles
    cv::min(cv::max(grey, 0.0), 1.0, grey);

    // The glass is what surrounds the tissue: bright glass means brightfield, and we invert so
    // tissue is bright in both cases.
    const float glass = borderMedian(grey, valid);
    out.contrast = glass > 0.5f ? Contrast::Brightfield : Contrast::Fluorescence;
    if (out.contrast == Contrast::Brightfield) {
        grey = 1.0f - grey;
        level = 1.0f - level;
    }
    const float glassLevel = out.contrast == Contrast::Brightfield ? 1.0f - glass : glass;
    const cv::Mat noData = ~valid;
    grey.setTo(glassLevel, noData);
    level.setTo(glassLevel, noData);

    // Uneven illumination (vignetting) makes glass corners look like tissue: flatten the glass
    // with a smooth fit (in place, both images; neither is touched when too little glass is seen
    // for a fit), then segment again. The fine mask is wanted of the final pass only.
    cv::Mat fineMask;
    cv::Mat mask = segmentTissue(grey, valid, glassLevel);
    flattenBackground(grey, valid, mask, glassLevel, level);
    out.grey = grey;
    out.level = level;
    mask = segmentTissue(grey, valid, glassLevel, &fineMask);

    // Remove debris: keep components of at least 2% of the largest one, and smaller ones down
    // to kMinFragmentShare of it that are solid (their inscribed radius at least
    // kMinFragmentRadius of the largest's equivalent radius, about 75 um on a 5 mm wide
    // section): a detached piece of tissue is a filled patch, while dust, fibres and bubble
    // rings are specks or lines a few pixels thin (docs/damage.md, "Small detached fragments").
    cv::Mat labels, stats;
    const int n = labelComponents(mask, labels, stats);
    int largest = 0;
    for (int i = 1; i < n; ++i)
        largest = std::max(largest, stats.at<int>(i, cv::CC_STAT_AREA));
    // One pass through a per-label table (a comparison of the whole image per component costs
    // as many passes as there are specks of debris).
    std::vector<uchar> kept(size_t(std::max(n, 1)), 0);
    std::vector<int> candidates; // smaller pieces, whole in the frame, to be judged by body
    for (int i = 1; i < n; ++i) {
        const int area = stats.at<int>(i, cv::CC_STAT_AREA);
        if (area >= std::max(16, largest / 50)) {
            kept[size_t(i)] = 255;
            continue;
        }
        // A piece cut by the image's edge is not seen whole (often a neighbouring section's
        // part reaching into the frame): only whole pieces are judged as fragments.
        const int x0 = stats.at<int>(i, cv::CC_STAT_LEFT), y0 = stats.at<int>(i, cv::CC_STAT_TOP);
        const bool whole = x0 > 0 && y0 > 0 &&
                           x0 + stats.at<int>(i, cv::CC_STAT_WIDTH) < mask.cols &&
                           y0 + stats.at<int>(i, cv::CC_STAT_HEIGHT) < mask.rows;
        if (whole && area >= std::max(16.0, kMinFragmentShare * largest))
            candidates.push_back(i);
    }
    if (!candidates.empty()) {
        // Inscribed radius per piece: the largest distance to the glass inside it.
        std::vector<float> inscribed(size_t(n), 0.0f);
        cv::Mat dist;
        cv::distanceTransform(mask, dist, cv::DIST_L2, 3);
        for (int y = 0; y < dist.rows; ++y) {
            const int* l = labels.ptr<int>(y);
            const float* d = dist.ptr<float>(y);
            for (int x = 0; x < dist.cols; ++x)
                inscribed[size_t(l[x])] = std::max(inscribed[size_t(l[x])], d[x]);
        }
        const double minRadius = kMinFragmentRadius * std::sqrt(largest / CV_PI);
        for (int i : candidates)
            kept[size_t(i)] = inscribed[size_t(i)] >= minRadius ? 255 : 0;
    }
    cv::Mat keep(mask.size(), CV_8U);
    for (int y = 0; y < keep.rows; ++y) {
        const int* l = labels.ptr<int>(y);
        uchar* k = keep.ptr<uchar>(y);
        for (int x = 0; x < keep.cols; ++x)
            k[x] = kept[size_t(l[x])];
    }
    const double share = cv::countNonZero(keep) / double(keep.total());
    if (share < 0.01)
        return makeError(ErrorCode::NoTissue, "no tissue found (tissue covers " +
                                                  std::to_string(share * 100) + "% of the image)");
    if (share > 0.97)
        return makeError(
            ErrorCode::NoTissue,
            "no tissue found: no glass around the tissue to tell it from the background");
    // Pure noise also splits into "tissue" and "glass"; real tissue stands well clear of the
    // glass noise.
    cv::Scalar inMean, inSd, outMean, outSd;
    cv::meanStdDev(grey, inMean, inSd, keep);
    cv::meanStdDev(grey, outMean, outSd, ~keep & valid);
    if (inMean[0] - outMean[0] < 1.0 * std::max(outSd[0], 1e-3))
        return makeError(ErrorCode::NoTissue,
                         "no tissue found (nothing stands out from the background)");
    out.tissueMask = keep;
    out.tissueMaskFine = fineMask & keep;
    out.smallPiecesFine = fineMask & ~keep;
    return out;
}

} // namespace slicestation::pipeline
