// Known random warps of a real section (issue 17, item 3): a random affine plus a smooth field,
// as slst_bench_consistency warps each section and the real-series tests reproduce one of its
// warps. Header-only, for the benchmarks and the tests.
#pragma once

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <random>
#include <vector>

namespace testing_warp {

constexpr double kPi = 3.14159265358979323846;

/// A known warp: new px q -> original px p = A q + s(q), s smooth (coarse grid, bilinear).
struct Warp {
    cv::Matx23d affine;
    cv::Mat sx, sy; ///< coarse displacement, original px, at q = (i, j) * step
    int step = 16;
    cv::Size size; ///< new image size

    cv::Point2d operator()(cv::Point2d q) const {
        const double fx = std::clamp(q.x / step, 0.0, sx.cols - 1.001);
        const double fy = std::clamp(q.y / step, 0.0, sx.rows - 1.001);
        const int x0 = int(fx), y0 = int(fy);
        const double wx = fx - x0, wy = fy - y0;
        auto at = [&](const cv::Mat& m) {
            return (1 - wy) * ((1 - wx) * m.at<float>(y0, x0) + wx * m.at<float>(y0, x0 + 1)) +
                   wy * ((1 - wx) * m.at<float>(y0 + 1, x0) + wx * m.at<float>(y0 + 1, x0 + 1));
        };
        return {affine(0, 0) * q.x + affine(0, 1) * q.y + affine(0, 2) + at(sx),
                affine(1, 0) * q.x + affine(1, 1) * q.y + affine(1, 2) + at(sy)};
    }
};

/// Random warp of an image of `size`: rotation within +/-15 degrees, per-axis scale within
/// +/-8%, shear within +/-0.05, shift within 3% of the size, and a smooth field of about 1% of
/// the longer side (s.d.) with features a quarter of the image across. The new image is 15%
/// larger so the turned section stays inside.
/// With `shiftOnly`, a whole-pixel shift into the larger image and nothing else: a check of the
/// benchmark itself (the registration should then agree with itself almost exactly); with
/// `sameFrame` too, a whole-pixel shift of up to 4% each way inside the image's own frame (the
/// same image size: only where the tissue lies in the frame changes).
inline Warp randomWarp(std::mt19937_64& rng, cv::Size size, bool shiftOnly, double fieldScale,
                       bool sameFrame = false) {
    auto U = [&](double a, double b) { return std::uniform_real_distribution<double>(a, b)(rng); };
    Warp w;
    w.size = cv::Size(int(size.width * 1.15), int(size.height * 1.15));
    if (shiftOnly) {
        if (sameFrame) { // whole pixels, up to 4% each way, in the image's own frame
            w.size = size;
            w.affine = cv::Matx23d(1, 0, std::floor(U(-0.04, 0.04) * size.width), 0, 1,
                                   std::floor(U(-0.04, 0.04) * size.height));
        } else {
            w.affine = cv::Matx23d(1, 0, -std::floor(U(0, 0.15) * size.width), 0, 1,
                                   -std::floor(U(0, 0.15) * size.height));
        }
        w.sx = cv::Mat::zeros(w.size.height / w.step + 2, w.size.width / w.step + 2, CV_32F);
        w.sy = w.sx.clone();
        return w;
    }
    const double rot = U(-15, 15) * kPi / 180, sx = 1 + U(-0.08, 0.08), sy = 1 + U(-0.08, 0.08),
                 sh = U(-0.05, 0.05);
    const cv::Matx22d R(std::cos(rot), -std::sin(rot), std::sin(rot), std::cos(rot));
    const cv::Matx22d L = R * cv::Matx22d(sx, sh, 0, sy);
    const cv::Vec2d cNew(w.size.width / 2.0, w.size.height / 2.0);
    const cv::Vec2d cOld(size.width / 2.0 + U(-0.03, 0.03) * size.width,
                         size.height / 2.0 + U(-0.03, 0.03) * size.height);
    const cv::Vec2d t = cOld - L * cNew;
    w.affine = cv::Matx23d(L(0, 0), L(0, 1), t[0], L(1, 0), L(1, 1), t[1]);
    const int side = std::max(size.width, size.height);
    w.step = std::max(4, side / 64);
    const int cols = w.size.width / w.step + 2, rows = w.size.height / w.step + 2;
    w.sx.create(rows, cols, CV_32F);
    w.sy.create(rows, cols, CV_32F);
    std::normal_distribution<float> n(0, 1);
    for (cv::Mat* m : {&w.sx, &w.sy}) {
        for (int r = 0; r < rows; ++r)
            for (int c = 0; c < cols; ++c)
                m->at<float>(r, c) = n(rng);
        const double sigma = 0.25 * side / w.step / 2;
        cv::GaussianBlur(*m, *m, cv::Size(), sigma, sigma, cv::BORDER_REFLECT);
        cv::Scalar mean, sd;
        cv::meanStdDev(*m, mean, sd);
        *m = (*m - mean[0]) * (fieldScale * 0.01 * side / std::max(1e-9, sd[0]));
    }
    return w;
}

/// The glass colour: per-channel median of the image's outer ring.
inline cv::Scalar glassOf(const cv::Mat& image) {
    cv::Scalar out;
    std::vector<cv::Mat> ch;
    cv::split(image, ch);
    for (size_t c = 0; c < ch.size() && c < 4; ++c) {
        std::vector<float> v;
        const cv::Mat& m = ch[c];
        cv::Mat f;
        m.convertTo(f, CV_32F);
        const int b = std::max(2, std::min(f.rows, f.cols) / 50);
        for (int r = 0; r < f.rows; ++r)
            for (int x = 0; x < f.cols; ++x)
                if (r < b || x < b || r >= f.rows - b || x >= f.cols - b)
                    v.push_back(f.at<float>(r, x));
        std::nth_element(v.begin(), v.begin() + std::ptrdiff_t(v.size() / 2), v.end());
        out[int(c)] = v[v.size() / 2];
    }
    return out;
}

inline cv::Mat applyWarp(const cv::Mat& image, const Warp& w) {
    cv::Mat mx(w.size, CV_32F), my(w.size, CV_32F), out;
    for (int y = 0; y < w.size.height; ++y)
        for (int x = 0; x < w.size.width; ++x) {
            const cv::Point2d p = w(cv::Point2d(x, y));
            mx.at<float>(y, x) = float(p.x);
            my.at<float>(y, x) = float(p.y);
        }
    cv::remap(image, out, mx, my, cv::INTER_LINEAR, cv::BORDER_CONSTANT, glassOf(image));
    return out;
}

/// How far two mappings of one section disagree under a known warp: over a grid of the warped
/// image (about 150 points per side) whose points `w` takes into `tissue` (CV_8U, the original's
/// pixels), the distance between `mapNew(q)` and `mapOld(w(q))`.
struct WarpDifference {
    double sumSq = 0, max = 0;
    long points = 0;
    double rms() const { return points > 0 ? std::sqrt(sumSq / double(points)) : 0.0; }
};

template <class MapNew, class MapOld>
WarpDifference differenceOverTissue(const Warp& w, const cv::Mat& tissue, MapNew mapNew,
                                    MapOld mapOld) {
    WarpDifference out;
    const int step = std::max(2, std::max(w.size.width, w.size.height) / 150);
    for (int y = 0; y < w.size.height; y += step)
        for (int x = 0; x < w.size.width; x += step) {
            const cv::Point2d p = w(cv::Point2d(x, y));
            const int px = int(std::lround(p.x)), py = int(std::lround(p.y));
            if (px < 0 || py < 0 || px >= tissue.cols || py >= tissue.rows ||
                !tissue.at<std::uint8_t>(py, px))
                continue;
            const double d = cv::norm(mapNew(cv::Point2d(x, y)) - mapOld(p));
            out.sumSq += d * d;
            out.max = std::max(out.max, d);
            ++out.points;
        }
    return out;
}

} // namespace testing_warp
