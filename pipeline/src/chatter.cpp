#include "slicestation/pipeline/chatter.hpp"

#include "slicestation/pipeline/mask_ops.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdlib>

namespace slicestation::pipeline {
namespace {

struct TilePeak {
    cv::Rect tile;
    int u = 0, v = 0; ///< the peak's DFT bin (u >= 0, v signed)
    double swing = 0;
};

/// One frequency: the same bin within one, or its mirror (the DFT of a real signal is symmetric).
bool sameFrequency(const TilePeak& a, const TilePeak& b) {
    return (std::abs(a.u - b.u) <= 1 && std::abs(a.v - b.v) <= 1) ||
           (std::abs(a.u + b.u) <= 1 && std::abs(a.v + b.v) <= 1);
}

} // namespace

std::vector<DamageRegion> chatterBands(const cv::Mat& grey, const cv::Mat& tissueMask,
                                       double brainWidthPx, const DamageParams& params) {
    CV_Assert(grey.type() == CV_32F && tissueMask.type() == CV_8U &&
              grey.size() == tissueMask.size());
    std::vector<DamageRegion> out;
    const double tissueArea = cv::countNonZero(tissueMask);
    if (params.chatterTiles <= 0 || brainWidthPx <= 0 || tissueArea <= 0)
        return out;
    // The level relative to the local mean of the tissue (a quarter of sigma per pixel of its
    // reduced copy): the swing, whatever the stain; taken away from the edge, where the local
    // mean mixes in the glass, and 0 there.
    const double sigma = std::max(2.0, params.chatterLevelFrac * brainWidthPx);
    cv::Mat weight;
    tissueMask.convertTo(weight, CV_32F, 1.0 / 255.0);
    const cv::Mat level =
        weightedLocalMean(grey, weight, sigma, std::max(1, static_cast<int>(sigma / 4)));
    cv::Mat toGlass;
    cv::distanceTransform(tissueMask, toGlass, cv::DIST_L2, 3);
    const cv::Mat inner = toGlass > std::max(1.0, 0.5 * sigma);
    cv::Mat relative(grey.size(), CV_32F);
    for (int y = 0; y < grey.rows; ++y) {
        const float* g = grey.ptr<float>(y);
        const float* l = level.ptr<float>(y);
        const std::uint8_t* in = inner.ptr<std::uint8_t>(y);
        float* r = relative.ptr<float>(y);
        for (int x = 0; x < grey.cols; ++x)
            r[x] = in[x] ? g[x] / std::max(l[x], 1e-3f) - 1.0f : 0.0f;
    }

    int side = 16;
    while (side < params.chatterTileFrac * brainWidthPx)
        side *= 2;
    cv::Mat hann;
    cv::createHanningWindow(hann, cv::Size(side, side), CV_32F);
    const double windowSum = cv::sum(hann)[0];
    const double shortest = params.chatterPeriodFrac[0] * brainWidthPx,
                 longest = params.chatterPeriodFrac[1] * brainWidthPx;
    // The DFT bins whose period lies in the band, once: (row, column, signed vertical bin).
    struct Bin {
        int row, u, v;
    };
    std::vector<Bin> band;
    for (int row = 0; row < side; ++row)
        for (int u = 0; u <= side / 2; ++u) {
            const int v = row <= side / 2 ? row : row - side;
            const double cycles = std::hypot(u, v);
            if (cycles > 0 && side / cycles >= shortest && side / cycles <= longest)
                band.push_back({row, u, v});
        }
    std::vector<TilePeak> peaks;
    if (band.empty())
        return out;
    cv::Mat spectrum;
    for (int y = 0; y + side <= grey.rows; y += side / 2)
        for (int x = 0; x + side <= grey.cols; x += side / 2) {
            const cv::Rect tile(x, y, side, side);
            if (cv::countNonZero(inner(tile)) < 0.9 * side * side)
                continue;
            cv::dft(relative(tile).mul(hann), spectrum, cv::DFT_COMPLEX_OUTPUT);
            TilePeak best{tile};
            double strongest = 0;
            for (const Bin& b : band) {
                const cv::Vec2f z = spectrum.at<cv::Vec2f>(b.row, b.u);
                const double power = double(z[0]) * z[0] + double(z[1]) * z[1];
                if (power > strongest) {
                    strongest = power;
                    best.u = b.u;
                    best.v = b.v;
                }
            }
            strongest = std::sqrt(strongest);
            // A sinusoid of amplitude a under the window gives a / 2 of the window's sum.
            best.swing = 2 * strongest / windowSum;
            if (best.swing >= params.chatterSwing)
                peaks.push_back(best);
        }
    // The largest set of strong tiles sharing one frequency.
    std::vector<const TilePeak*> pattern;
    for (const TilePeak& p : peaks) {
        std::vector<const TilePeak*> same;
        for (const TilePeak& q : peaks)
            if (sameFrequency(p, q))
                same.push_back(&q);
        if (same.size() > pattern.size())
            pattern = std::move(same);
    }
    // The knife's one period dominates: tissue's texture at the same scale (cells, their
    // spacing) makes strong tiles too, but their peaks scatter over every direction.
    if (static_cast<int>(pattern.size()) < params.chatterTiles ||
        double(pattern.size()) < params.chatterDominance * double(peaks.size()))
        return out;
    cv::Mat region = cv::Mat::zeros(grey.size(), CV_8U);
    double swing = 0;
    for (const TilePeak* p : pattern) {
        region(p->tile).setTo(255);
        swing += p->swing / double(pattern.size());
    }
    region &= tissueMask;
    std::vector<std::vector<cv::Point>> contours;
    cv::findContours(region.clone(), contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_SIMPLE);
    if (contours.empty())
        return out;
    std::vector<cv::Point> all;
    for (const auto& c : contours)
        all.insert(all.end(), c.begin(), c.end());
    std::vector<cv::Point> hull;
    cv::convexHull(all, hull);
    DamageRegion d;
    d.kind = DamageKind::Chatter;
    for (const cv::Point& p : hull)
        d.polygon.emplace_back(float(p.x), float(p.y));
    d.areaPx = cv::countNonZero(region);
    d.share = d.areaPx / tissueArea;
    const cv::Rect box = cv::boundingRect(hull);
    d.lengthPx = std::max(box.width, box.height);
    d.levelShare = swing; // the mean swing of the pattern's tiles
    const TilePeak& first = *pattern.front();
    d.thicknessPx = side / std::max(1e-9, std::hypot(first.u, first.v)); // the period
    out.push_back(std::move(d));
    return out;
}

} // namespace slicestation::pipeline
