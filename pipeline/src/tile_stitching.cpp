#include "slicestation/pipeline/tile_stitching.hpp"

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <optional>
#include <string>

namespace slicestation::pipeline {
namespace {

using core::ErrorCode;
using core::makeError;

constexpr int kMinOverlapPx = 16;
constexpr double kMinResponse = 0.1;
constexpr double kPriorWeight = 1e-3; // stage positions vs measured offsets (weight 1)
constexpr int kMaxMosaicSidePx = 40'000;

/// Centres along one axis: evenly spaced, overlapping by at least `overlap` of a field.
std::vector<double> axisCentres(double centre, double extent, double field, double overlap) {
    if (extent <= field)
        return {centre};
    const double maxStep = field * (1 - overlap);
    const int n = static_cast<int>(std::ceil((extent - field) / maxStep - 1e-9)) + 1;
    const double step = (extent - field) / (n - 1);
    std::vector<double> out;
    const double first = centre - extent / 2 + field / 2;
    for (int i = 0; i < n; ++i)
        out.push_back(first + i * step);
    return out;
}

cv::Mat greyFloat(const cv::Mat& image) {
    cv::Mat grey;
    if (image.channels() == 1) {
        grey = image;
    } else if (image.channels() == 3) {
        cv::cvtColor(image, grey, cv::COLOR_BGR2GRAY);
    } else if (image.channels() == 4) {
        cv::cvtColor(image, grey, cv::COLOR_BGRA2GRAY);
    } else {
        cv::extractChannel(image, grey, 0);
    }
    cv::Mat f;
    grey.convertTo(f, CV_32F);
    return f;
}

/// False for a (nearly) uniform patch, whose phase correlation peak is meaningless.
bool hasStructure(const cv::Mat& patch) {
    cv::Scalar mean;
    cv::Scalar stddev;
    cv::meanStdDev(patch, mean, stddev);
    return stddev[0] > 1e-3 * std::abs(mean[0]) + 1e-6;
}

/// Largest even n' <= n whose DFT OpenCV computes without padding (products of 2, 3 and 5):
/// phaseCorrelate pads odd sizes and then reports a half-pixel bias.
int evenDftSize(int n) {
    for (int m = n - (n % 2); m >= 2; m -= 2) {
        if (cv::getOptimalDFTSize(m) == m)
            return m;
    }
    return 0;
}

/// Top-left of tile j minus top-left of tile i (px), measured by phase correlation on their
/// overlap, starting from the stage's `guess`; nullopt when there is no reliable measurement.
std::optional<cv::Point2d> measureOffset(const cv::Mat& gi, const cv::Mat& gj, cv::Point guess) {
    const cv::Rect first = cv::Rect(cv::Point(0, 0), gi.size()) & cv::Rect(guess, gj.size());
    if (first.width < kMinOverlapPx || first.height < kMinOverlapPx)
        return std::nullopt;
    const double bound = std::max(2.0, 0.25 * std::min(first.width, first.height));
    cv::Point g = guess;
    cv::Point2d s;
    bool converged = false;
    // Each pass re-cuts the overlap at the current estimate; the last pass measures a shift
    // near zero, where the Hann window does not bias the peak.
    for (int pass = 0; pass < 4; ++pass) {
        cv::Rect a = cv::Rect(cv::Point(0, 0), gi.size()) & cv::Rect(g, gj.size());
        const int w = evenDftSize(a.width);
        const int h = evenDftSize(a.height);
        if (w < kMinOverlapPx || h < kMinOverlapPx)
            return std::nullopt;
        a = cv::Rect(a.x + (a.width - w) / 2, a.y + (a.height - h) / 2, w, h);
        const cv::Mat pi = gi(a);
        const cv::Mat pj = gj(a - g);
        if (!hasStructure(pi) || !hasStructure(pj)) {
            return std::nullopt; // uniform glass: nothing to lock on to
        }
        cv::Mat window;
        cv::createHanningWindow(window, a.size(), CV_32F);
        double response = 0;
        // pi(u) shows the world at u + a.tl() + T_i and pj(u) at u + a.tl() - g + T_j, so
        // pj(u) = pi(u - s) with s = g - (T_j - T_i): the offset is g - s.
        // Copies: when no padding is needed, OpenCV 4.6 applies the window in place, through
        // the const input, which would corrupt the tiles for the next pair.
        s = cv::phaseCorrelate(pi.clone(), pj.clone(), window, &response);
        if (!(response >= kMinResponse) || !std::isfinite(s.x) || !std::isfinite(s.y)) {
            return std::nullopt;
        }
        const cv::Point next(static_cast<int>(std::lround(g.x - s.x)),
                             static_cast<int>(std::lround(g.y - s.y)));
        if (next == g) {
            converged = true;
            break;
        }
        if (std::abs(next.x - guess.x) > bound || std::abs(next.y - guess.y) > bound) {
            return std::nullopt;
        }
        g = next;
    }
    if (!converged)
        return std::nullopt; // the estimate kept moving: not reliable
    const cv::Point2d d = cv::Point2d(g) - s;
    if (std::abs(d.x - guess.x) > bound || std::abs(d.y - guess.y) > bound)
        return std::nullopt;
    return d;
}

struct Offset {
    int i = 0;
    int j = 0;
    cv::Point2d d; ///< measured top-left of j minus top-left of i, px
};

/// Linear weights: distance (px) to the tile's nearest border, at least 1.
cv::Mat borderDistance(cv::Size size) {
    cv::Mat w(size, CV_32F);
    for (int y = 0; y < size.height; ++y) {
        auto* row = w.ptr<float>(y);
        const int dy = std::min(y + 1, size.height - y);
        for (int x = 0; x < size.width; ++x) {
            row[x] = static_cast<float>(std::min(dy, std::min(x + 1, size.width - x)));
        }
    }
    return w;
}

core::Result<cv::Mat> stitch(const std::vector<Tile>& tiles, double umPerPx, bool refine) {
    const auto bad = [](const std::string& what) {
        return makeError(ErrorCode::InvalidArgument, "stitchTiles: " + what);
    };
    if (tiles.empty())
        return bad("no tiles");
    if (!(umPerPx > 0) || !std::isfinite(umPerPx))
        return bad("umPerPx must be > 0");
    const int type = tiles.front().image.type();
    const int depth = CV_MAT_DEPTH(type);
    const int channels = CV_MAT_CN(type);
    if ((depth != CV_8U && depth != CV_16U && depth != CV_32F) || channels > 4) {
        return bad("unsupported image type " + cv::typeToString(type));
    }
    for (std::size_t k = 0; k < tiles.size(); ++k) {
        const auto& t = tiles[k];
        const std::string which = "tile " + std::to_string(k);
        if (t.image.empty())
            return bad(which + " is empty");
        if (t.image.type() != type)
            return bad(which + " differs in type from tile 0");
        if (!std::isfinite(t.stage.xUm) || !std::isfinite(t.stage.yUm)) {
            return bad(which + " has a non-finite stage position");
        }
    }

    const int n = static_cast<int>(tiles.size());
    // Nominal top-left corners from the stage positions, px.
    std::vector<cv::Point2d> nominal(tiles.size());
    for (int k = 0; k < n; ++k) {
        const auto& t = tiles[k];
        nominal[k] = {t.stage.xUm / umPerPx - t.image.cols / 2.0,
                      t.stage.yUm / umPerPx - t.image.rows / 2.0};
    }
    // Reject nonsense before anything is allocated.
    double minX = 1e300, minY = 1e300, maxX = -1e300, maxY = -1e300;
    for (int k = 0; k < n; ++k) {
        const auto& p = nominal[k];
        const auto& im = tiles[k].image;
        minX = std::min(minX, p.x);
        minY = std::min(minY, p.y);
        maxX = std::max(maxX, p.x + im.cols);
        maxY = std::max(maxY, p.y + im.rows);
    }
    if (maxX - minX > kMaxMosaicSidePx - 64 || maxY - minY > kMaxMosaicSidePx - 64) {
        return bad("the tiles span more than " + std::to_string(kMaxMosaicSidePx) +
                   " px a side (check the stage positions and umPerPx)");
    }

    std::vector<Offset> offsets;
    if (refine && n > 1) {
        std::vector<cv::Mat> grey(tiles.size());
        for (int k = 0; k < n; ++k)
            grey[k] = greyFloat(tiles[k].image);
        for (int i = 0; i < n; ++i) {
            for (int j = i + 1; j < n; ++j) {
                const cv::Point guess(static_cast<int>(std::lround(nominal[j].x - nominal[i].x)),
                                      static_cast<int>(std::lround(nominal[j].y - nominal[i].y)));
                if (auto d = measureOffset(grey[i], grey[j], guess)) {
                    offsets.push_back({i, j, *d});
                }
            }
        }
    }

    // Least squares for all top-left corners: offsets (weight 1) and stage placement (weak).
    std::vector<cv::Point2d> placed = nominal;
    if (!offsets.empty()) {
        cv::Mat a = cv::Mat::eye(n, n, CV_64F) * kPriorWeight;
        cv::Mat b(n, 2, CV_64F);
        for (int k = 0; k < n; ++k) {
            b.at<double>(k, 0) = kPriorWeight * nominal[k].x;
            b.at<double>(k, 1) = kPriorWeight * nominal[k].y;
        }
        for (const auto& o : offsets) {
            a.at<double>(o.i, o.i) += 1;
            a.at<double>(o.j, o.j) += 1;
            a.at<double>(o.i, o.j) -= 1;
            a.at<double>(o.j, o.i) -= 1;
            b.at<double>(o.j, 0) += o.d.x;
            b.at<double>(o.j, 1) += o.d.y;
            b.at<double>(o.i, 0) -= o.d.x;
            b.at<double>(o.i, 1) -= o.d.y;
        }
        cv::Mat solution;
        if (cv::solve(a, b, solution, cv::DECOMP_CHOLESKY)) {
            for (int k = 0; k < n; ++k) {
                placed[k] = {solution.at<double>(k, 0), solution.at<double>(k, 1)};
            }
        }
    }

    // Whole pixels relative to the first tile: the measured offsets are near-integers, so this
    // rounding is exact for them whatever the common sub-pixel offset.
    std::vector<cv::Point> corner(tiles.size());
    cv::Point minCorner(INT32_MAX, INT32_MAX);
    cv::Point maxCorner(INT32_MIN, INT32_MIN);
    for (int k = 0; k < n; ++k) {
        const cv::Point2d rel = placed[k] - placed[0];
        corner[k] = {static_cast<int>(std::lround(rel.x)), static_cast<int>(std::lround(rel.y))};
        const auto& im = tiles[k].image;
        minCorner.x = std::min(minCorner.x, corner[k].x);
        minCorner.y = std::min(minCorner.y, corner[k].y);
        maxCorner.x = std::max(maxCorner.x, corner[k].x + im.cols);
        maxCorner.y = std::max(maxCorner.y, corner[k].y + im.rows);
    }
    const cv::Size size(maxCorner.x - minCorner.x, maxCorner.y - minCorner.y);
    if (size.width > kMaxMosaicSidePx || size.height > kMaxMosaicSidePx) {
        return bad("the refined mosaic exceeds " + std::to_string(kMaxMosaicSidePx) + " px a side");
    }

    cv::Mat sum(size, CV_32FC(channels), cv::Scalar::all(0));
    cv::Mat weightSum(size, CV_32F, cv::Scalar(0));
    for (int k = 0; k < n; ++k) {
        const cv::Mat& im = tiles[k].image;
        const cv::Rect where(corner[k] - minCorner, im.size());
        cv::Mat f;
        im.convertTo(f, CV_32F);
        const cv::Mat w = borderDistance(im.size());
        cv::Mat weighted;
        if (channels == 1) {
            weighted = f.mul(w);
        } else {
            std::vector<cv::Mat> planes;
            cv::split(f, planes);
            for (auto& p : planes)
                p = p.mul(w);
            cv::merge(planes, weighted);
        }
        cv::Mat target = sum(where);
        target += weighted;
        cv::Mat wTarget = weightSum(where);
        wTarget += w;
    }
    cv::Mat norm = cv::max(weightSum, 1e-6F);
    cv::Mat mosaic;
    if (channels == 1) {
        cv::divide(sum, norm, mosaic);
    } else {
        std::vector<cv::Mat> planes;
        cv::split(sum, planes);
        for (auto& p : planes)
            cv::divide(p, norm, p);
        cv::merge(planes, mosaic);
    }
    cv::Mat out;
    mosaic.convertTo(out, type); // rounds and saturates
    return out;
}

} // namespace

TilePlan planTiles(const hw::StagePosition& centre, double widthUm, double heightUm,
                   double fieldWidthUm, double fieldHeightUm, double overlapFraction) {
    const bool valid = std::isfinite(centre.xUm) && std::isfinite(centre.yUm) &&
                       std::isfinite(widthUm) && std::isfinite(heightUm) && widthUm >= 0 &&
                       heightUm >= 0 && fieldWidthUm > 0 && fieldHeightUm > 0 &&
                       std::isfinite(fieldWidthUm) && std::isfinite(fieldHeightUm) &&
                       overlapFraction >= 0 && overlapFraction <= 0.9;
    if (!valid)
        return {};
    const auto xs = axisCentres(centre.xUm, widthUm, fieldWidthUm, overlapFraction);
    const auto ys = axisCentres(centre.yUm, heightUm, fieldHeightUm, overlapFraction);
    TilePlan plan;
    plan.columns = static_cast<int>(xs.size());
    plan.rows = static_cast<int>(ys.size());
    for (const double y : ys) {
        for (const double x : xs)
            plan.centres.push_back({x, y, centre.zUm});
    }
    return plan;
}

core::Result<cv::Mat> stitchTiles(const std::vector<Tile>& tiles, double umPerPx,
                                  bool refineWithPhaseCorrelation) {
    try {
        return stitch(tiles, umPerPx, refineWithPhaseCorrelation);
    } catch (const cv::Exception& e) {
        return makeError(ErrorCode::Internal, std::string("stitchTiles: OpenCV: ") + e.what());
    } catch (const std::exception& e) {
        return makeError(ErrorCode::Internal, std::string("stitchTiles: ") + e.what());
    }
}

} // namespace slicestation::pipeline
