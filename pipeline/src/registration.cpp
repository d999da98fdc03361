#include "slicestation/pipeline/registration.hpp"

#include "side_by_side.hpp"
#include "slicestation/pipeline/affine.hpp"
#include "slicestation/pipeline/chatter.hpp"
#include "slicestation/pipeline/damage_series.hpp"
#include "slicestation/pipeline/icp.hpp"
#include "slicestation/pipeline/intensity_affine.hpp"
#include "slicestation/pipeline/intensity_warp.hpp"
#include "slicestation/pipeline/mask_ops.hpp"
#include "slicestation/pipeline/obb.hpp"
#include "slicestation/pipeline/point_grid.hpp"
#include "slicestation/pipeline/smooth_warp.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <ctime>
#include <functional>
#include <limits>
#include <optional>
#include <utility>

namespace slicestation::pipeline {
namespace {

using core::ErrorCode;
using core::makeError;
using Clock = std::chrono::steady_clock;

/// CPU time of the whole process (all threads) in milliseconds.
double processCpuMs() {
    timespec ts{};
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
    return double(ts.tv_sec) * 1e3 + double(ts.tv_nsec) * 1e-6;
}

/// CPU time of the calling thread in milliseconds.
double threadCpuMs() {
    timespec ts{};
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
    return double(ts.tv_sec) * 1e3 + double(ts.tv_nsec) * 1e-6;
}

/// Times each step (wall and process CPU) and reports it done to the options' progress
/// callback.
class StepTimer {
public:
    StepTimer(std::vector<std::pair<std::string, double>>& out,
              std::vector<std::pair<std::string, double>>& cpu,
              const std::function<void(int, int)>& progress)
        : out_(out), cpu_(cpu), progress_(progress) {}
    /// Ends the step `name`; `step` false: a part timed on its own that is not a step of the
    /// progress count.
    void lap(const char* name, bool step = true) {
        const auto now = Clock::now();
        const double cpuNow = processCpuMs();
        out_.emplace_back(name, std::chrono::duration<double, std::milli>(now - last_).count());
        cpu_.emplace_back(name, cpuNow - cpuLast_);
        last_ = now;
        cpuLast_ = cpuNow;
        if (progress_ && step)
            progress_(std::min(++done_, kRegistrationSteps), kRegistrationSteps);
    }
    /// Records the step `name` timed on another thread (its own wall and CPU time), after the
    /// steps it ran beside; the next lap still starts where the previous one ended.
    void record(const char* name, double wallMs, double cpuMs) {
        out_.emplace_back(name, wallMs);
        cpu_.emplace_back(name, cpuMs);
        if (progress_)
            progress_(std::min(++done_, kRegistrationSteps), kRegistrationSteps);
    }
    void total() {
        out_.emplace_back("total",
                          std::chrono::duration<double, std::milli>(Clock::now() - start_).count());
        cpu_.emplace_back("total", processCpuMs() - cpuStart_);
        if (progress_)
            progress_(kRegistrationSteps, kRegistrationSteps);
    }

private:
    std::vector<std::pair<std::string, double>>& out_;
    std::vector<std::pair<std::string, double>>& cpu_;
    const std::function<void(int, int)>& progress_;
    int done_ = 0;
    Clock::time_point start_ = Clock::now(), last_ = start_;
    double cpuStart_ = processCpuMs(), cpuLast_ = cpuStart_;
};

/// Two placements whose section box ends lie this close (atlas px) are the same placement.
constexpr double kSamePlaceAtlasPx = 2.0;

/// A close placement whose edge agreement trails the leading one's by more than this after the
/// full ICP's third level is not run through the finest level: over the first family's 48 cases
/// the finest level moved a placement's agreement by at most 0.04, so it cannot catch up (see
/// docs/registration.md, "The finest ICP level for the leading placements only").
constexpr double kTrailingAgreement = 0.1;

/// Only placements whose overlap after the outline ICP is within this of the best one's are
/// polished by the overlap search (chosen on the first family, where no result moved; as above).
constexpr double kPolishBehind = 0.1;

/// SOR sweeps per level of the Laplace warp's rounds before the last (the last keeps
/// LaplaceOptions' 40): their fields only choose the next round's matches, whose reach is several
/// atlas px (docs/registration.md as above).
constexpr int kLaplaceSweepsBeforeLastRound = 20;

/// IoU of the section's (filled) tissue and the atlas brain mapped into the working frame.
double overlap(const cv::Mat& tissueFilled, const cv::Mat& atlasMask, const cv::Matx23d& t) {
    cv::Mat mapped;
    cv::warpAffine(atlasMask, mapped, cv::Mat(t), tissueFilled.size(),
                   cv::INTER_NEAREST | cv::WARP_INVERSE_MAP, cv::BORDER_CONSTANT, 0);
    const double inter = cv::countNonZero(mapped & tissueFilled);
    const double uni = cv::countNonZero(mapped | tissueFilled);
    return uni > 0 ? inter / uni : 0.0;
}

/// atlas = cA + L (p - cI): the linear part L with the section's OBB centre on the atlas's.
/// The rotation (degrees, in (-180, 180]) of an affine's linear part: the angle of its closest
/// rotation (polar decomposition).
double turnDegrees(const cv::Matx23d& t) {
    return std::atan2(t(1, 0) - t(0, 1), t(0, 0) + t(1, 1)) * 180 / CV_PI;
}

cv::Matx23d centreOnCentre(const cv::Matx22d& L, const OrientedBox& img, const OrientedBox& atl) {
    const cv::Vec2d c =
        cv::Vec2d(atl.centre.x, atl.centre.y) - L * cv::Vec2d(img.centre.x, img.centre.y);
    return {L(0, 0), L(0, 1), c[0], L(1, 0), L(1, 1), c[1]};
}

/// Initial placement from the two OBBs: centre on centre, axes on axes, per-axis scale (or the
/// known scale), with the sign choices that the 180-degree ambiguity (and mirroring) leaves.
cv::Matx23d obbPlacement(const OrientedBox& img, const OrientedBox& atl, double sMaj, double sMin,
                         bool swapAxes, double knownScale) {
    const cv::Vec2d aMaj = swapAxes ? atl.minor : atl.major;
    const cv::Vec2d aMin = swapAxes ? atl.major : atl.minor;
    const double hMaj = swapAxes ? atl.halfMinor : atl.halfMajor;
    const double hMin = swapAxes ? atl.halfMajor : atl.halfMinor;
    const double kMaj = knownScale > 0 ? knownScale : hMaj / std::max(img.halfMajor, 1e-9);
    const double kMin = knownScale > 0 ? knownScale : hMin / std::max(img.halfMinor, 1e-9);
    // atlas = cA + [aMaj aMin] diag(kMaj sMaj, kMin sMin) [iMaj iMin]^T (p - cI)
    const cv::Matx22d A(aMaj[0], aMin[0], aMaj[1], aMin[1]);
    const cv::Matx22d D(kMaj * sMaj, 0, 0, kMin * sMin);
    const cv::Matx22d It(img.major[0], img.major[1], img.minor[0], img.minor[1]);
    return centreOnCentre(A * D * It, img, atl);
}

/// The section's centre on the atlas's, turned by `degrees` and scaled by `scale` (atlas px per
/// working px).
cv::Matx23d rotatedPlacement(const OrientedBox& img, const OrientedBox& atl, int degrees,
                             double scale) {
    const double a = degrees * CV_PI / 180.0;
    return centreOnCentre(cv::Matx22d(scale * std::cos(a), -scale * std::sin(a),
                                      scale * std::sin(a), scale * std::cos(a)),
                          img, atl);
}

/// Overlap of the section's filled tissue and the atlas brain, evaluated on a small copy of the
/// tissue mask so that a search can afford hundreds of evaluations.
class OverlapScorer {
public:
    OverlapScorer(const cv::Mat& tissueFilled, const cv::Mat& atlasMask) : atlasMask_(atlasMask) {
        const int longSide = std::max(tissueFilled.cols, tissueFilled.rows);
        factor_ = std::min(1.0, 256.0 / longSide);
        cv::resize(tissueFilled, small_, cv::Size(), factor_, factor_, cv::INTER_AREA);
        small_ = small_ > 127;
        area_ = cv::countNonZero(small_);
    }
    /// IoU for an atlasFromWorking affine.
    double operator()(const cv::Matx23d& atlasFromWorking) const {
        const cv::Matx23d m = compose(atlasFromWorking, scaling(1.0 / factor_));
        cv::Mat mapped; // one per call: placements are scored side by side
        cv::warpAffine(atlasMask_, mapped, cv::Mat(m), small_.size(),
                       cv::INTER_NEAREST | cv::WARP_INVERSE_MAP, cv::BORDER_CONSTANT, 0);
        const double inter = cv::countNonZero(mapped & small_);
        const double uni = area_ + cv::countNonZero(mapped) - inter;
        return uni > 0 ? inter / uni : 0.0;
    }

private:
    cv::Mat atlasMask_, small_;
    double factor_ = 1.0;
    int area_ = 0;
};

/// Pattern search on the six affine parameters (about the tissue centre) for the best overlap:
/// masks do not have the local minima that outline details give ICP (two olfactory bulbs
/// touching in the section but apart in the atlas, say).
cv::Matx23d refineByOverlap(const OverlapScorer& score, cv::Matx23d t, cv::Point2d centre,
                            double size, double& best) {
    best = score(t);
    // Perturbations in the working frame: t' = t o (centre + (I + D)(p - centre) + d).
    double step[6] = {0.02 * size, 0.02 * size, 0.02, 0.02, 0.02, 0.02};
    for (int round = 0; round < 60; ++round) {
        bool improved = false;
        for (int k = 0; k < 6; ++k) {
            for (const double sign : {1.0, -1.0}) {
                double dx = 0, dy = 0, a = 1, b = 0, c = 0, d = 1;
                switch (k) {
                case 0:
                    dx = sign * step[0];
                    break;
                case 1:
                    dy = sign * step[1];
                    break;
                case 2:
                    a += sign * step[2];
                    break;
                case 3:
                    d += sign * step[3];
                    break;
                case 4:
                    b += sign * step[4];
                    break;
                default:
                    c += sign * step[5];
                    break;
                }
                const cv::Matx23d local(a, b, centre.x + dx - a * centre.x - b * centre.y, c, d,
                                        centre.y + dy - c * centre.x - d * centre.y);
                const cv::Matx23d cand = compose(t, local);
                const double v = score(cand);
                if (v > best + 1e-6) {
                    best = v;
                    t = cand;
                    improved = true;
                    break;
                }
            }
        }
        if (!improved) {
            for (double& st : step)
                st *= 0.5;
            if (step[2] < 0.001)
                break;
        }
    }
    return t;
}

/// ICP level by level on point sets thinned to suit each level's reach: a point every
/// distance/8 is plenty to steer a loose level, and it keeps the neighbour searches short.
IcpResult multiLevelIcp(const EdgePoints& source, const EdgePoints& target, cv::Matx23d init,
                        const std::vector<IcpLevel>& levels, int iterations,
                        double atlasPerSource) {
    IcpResult r;
    r.targetFromSource = init;
    for (const IcpLevel& level : levels) {
        const float spacing = float(level.distance / 8);
        const EdgePoints t = thinEdgePoints(target, spacing);
        const EdgePoints src = thinEdgePoints(source, float(spacing / atlasPerSource));
        const PointGrid grid(t.points, float(level.distance));
        IcpOptions o;
        o.levels = {level};
        o.maxIterationsPerLevel = iterations;
        r = icpAffine(src, t, grid, r.targetFromSource, o);
    }
    return r;
}

double shareMatched(const std::vector<cv::Point2f>& pts, const PointGrid& other, double tol) {
    if (pts.empty())
        return 0;
    size_t hit = 0;
    for (const auto& p : pts)
        if (other.nearest(p, float(tol)) >= 0)
            ++hit;
    return double(hit) / double(pts.size());
}

/// `section` mapped into the atlas through `atlasFromWorking` and `warp` (normals through the
/// affine).
void mapThrough(const EdgePoints& section, const cv::Matx23d& atlasFromWorking,
                const DisplacementField& warp, std::vector<cv::Point2f>& mapped,
                std::vector<cv::Point2f>& normals) {
    mapped.clear();
    normals.clear();
    mapped.reserve(section.size());
    normals.reserve(section.size());
    for (size_t i = 0; i < section.size(); ++i) {
        const cv::Point2d p = section.points[i];
        mapped.emplace_back(apply(atlasFromWorking, p) + warp.at(p));
        normals.push_back(mapNormal(atlasFromWorking, section.normals[i]));
    }
}

/// Warp conditions (section point, displacement from the affine) from the matches of
/// `section` mapped through `atlasFromWorking` and `warp` against `atlas`.
void addWarpConditions(const EdgePoints& section, const cv::Matx23d& atlasFromWorking,
                       const DisplacementField& warp, const EdgePoints& atlas,
                       const PointGrid& grid, double distance, double angleDeg,
                       std::vector<cv::Point2d>& points, std::vector<cv::Point2d>& displacements) {
    std::vector<cv::Point2f> mapped, normals;
    mapThrough(section, atlasFromWorking, warp, mapped, normals);
    for (const Match& m : findMatches(mapped, normals, atlas, grid, distance, angleDeg, true,
                                      TargetRule::PointToLine)) {
        const cv::Point2d p = section.points[size_t(m.source)];
        points.push_back(p);
        displacements.push_back(m.target - apply(atlasFromWorking, p));
    }
}

/// Jacobian determinant of working px -> atlas px (affine + warp) on the warp's nodes (CV_32F,
/// the node grid; empty without a warp).
cv::Mat mapJacobian(const cv::Matx23d& affine, const DisplacementField& warp) {
    if (warp.empty() || warp.dx().cols < 2 || warp.dx().rows < 2)
        return {};
    const double inv = 1.0 / warp.cellPx();
    cv::Mat xx, xy, yx, yy;
    cv::Sobel(warp.dx(), xx, CV_32F, 1, 0, 1, 0.5 * inv, affine(0, 0), cv::BORDER_REPLICATE);
    cv::Sobel(warp.dx(), xy, CV_32F, 0, 1, 1, 0.5 * inv, affine(0, 1), cv::BORDER_REPLICATE);
    cv::Sobel(warp.dy(), yx, CV_32F, 1, 0, 1, 0.5 * inv, affine(1, 0), cv::BORDER_REPLICATE);
    cv::Sobel(warp.dy(), yy, CV_32F, 0, 1, 1, 0.5 * inv, affine(1, 1), cv::BORDER_REPLICATE);
    return xx.mul(yy) - xy.mul(yx);
}

/// Smallest Jacobian determinant of working px -> atlas px (affine + warp) on the warp's nodes,
/// relative to the affine's.
double minJacobianRelative(const cv::Matx23d& affine, const DisplacementField& warp) {
    const cv::Mat j = mapJacobian(affine, warp);
    if (j.empty())
        return 1.0;
    double m = 0;
    cv::minMaxLoc(j, &m);
    return m / det(affine);
}

/// `warp` plus a displacement sampled on a reduced copy (`ux`, `uy`, CV_32F) of the working
/// domain `working` (cv::resize pixel-centre alignment); a warp with no nodes yet gets them.
DisplacementField addToWarp(const DisplacementField& warp, cv::Size working, const cv::Mat& ux,
                            const cv::Mat& uy) {
    cv::Mat dx = warp.empty() ? cv::Mat() : warp.dx().clone();
    cv::Mat dy = warp.empty() ? cv::Mat() : warp.dy().clone();
    double cell = warp.empty() ? 0 : warp.cellPx();
    if (warp.empty()) {
        cell = std::max(2.0, std::max(working.width, working.height) / 200.0);
        const int cols = static_cast<int>(std::ceil((working.width - 1) / cell)) + 1;
        const int rows = static_cast<int>(std::ceil((working.height - 1) / cell)) + 1;
        dx = cv::Mat::zeros(rows, cols, CV_32F);
        dy = cv::Mat::zeros(rows, cols, CV_32F);
    }
    const double fx = double(ux.cols) / working.width, fy = double(ux.rows) / working.height;
    cv::Mat mx(dx.size(), CV_32F), my(dx.size(), CV_32F);
    for (int i = 0; i < dx.rows; ++i)
        for (int j = 0; j < dx.cols; ++j) {
            mx.at<float>(i, j) = float((j * cell + 0.5) * fx - 0.5);
            my.at<float>(i, j) = float((i * cell + 0.5) * fy - 0.5);
        }
    cv::Mat ax, ay;
    cv::remap(ux, ax, mx, my, cv::INTER_LINEAR, cv::BORDER_REPLICATE);
    cv::remap(uy, ay, mx, my, cv::INTER_LINEAR, cv::BORDER_REPLICATE);
    return DisplacementField(dx + ax, dy + ay, cell);
}

/// The reduced grid (longer side at most `maxSide`) the dense stages work on.
cv::Size gridSize(cv::Size ws, int maxSide) {
    const double f = std::min(1.0, double(maxSide) / std::max(ws.width, ws.height));
    return {std::max(8, static_cast<int>(std::lround(ws.width * f))),
            std::max(8, static_cast<int>(std::lround(ws.height * f)))};
}

/// Where the dense stages measure, on a grid of `gs` (CV_8U): the tissue (holes filled) and a
/// glass band of 1% of the grid width round it, without excluded pixels, detached fragments
/// (grown by the band) and deep damaged concavities. The masks are reduced first (a grid pixel
/// counts when mostly tissue; any excluded share excludes it), then the band is grown there.
cv::Mat measuredArea(cv::Size gs, const cv::Mat& tissueFilled, const cv::Mat& excludeMask,
                     const cv::Mat& fragments, const cv::Mat& damagedOutline) {
    cv::Mat weight, excluded;
    cv::resize(tissueFilled, weight, gs, 0, 0, cv::INTER_AREA);
    weight = weight > 127;
    const int band = std::max(1, static_cast<int>(std::lround(gs.width / 100.0)));
    cv::dilate(weight, weight,
               cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * band + 1, 2 * band + 1)));
    auto exclude = [&](const cv::Mat& mask, int grownBy) {
        if (mask.empty())
            return;
        cv::resize(mask != 0, excluded, gs, 0, 0, cv::INTER_AREA);
        excluded = excluded > 0;
        if (grownBy > 0)
            cv::dilate(excluded, excluded,
                       cv::getStructuringElement(cv::MORPH_ELLIPSE,
                                                 cv::Size(2 * grownBy + 1, 2 * grownBy + 1)));
        weight.setTo(0, excluded);
    };
    exclude(excludeMask, 0);
    exclude(fragments, band);
    exclude(damagedOutline, 0);
    return weight;
}

/// Damage regions found on an image resized by `scale` from the section, in the full
/// section's pixels: polygon, area, length and thickness.
void toFullPixels(std::vector<DamageRegion>& regions, double scale) {
    for (DamageRegion& d : regions) {
        for (cv::Point2f& p : d.polygon)
            p = cv::Point2f(float((p.x + 0.5) / scale - 0.5), float((p.y + 0.5) / scale - 0.5));
        d.areaPx /= scale * scale;
        d.lengthPx /= scale;
        d.thicknessPx /= scale;
    }
}

} // namespace

cv::Point2d Registration::workingFromImage(cv::Point2d p) const {
    // cv::resize with INTER_AREA aligns pixel centres: x_w = (x + 0.5) s - 0.5.
    return {(p.x + 0.5) * workingScale - 0.5, (p.y + 0.5) * workingScale - 0.5};
}

cv::Matx23d Registration::affineAtlasFromImage() const {
    const double s = workingScale, o = 0.5 * s - 0.5;
    return compose(atlasFromWorking, cv::Matx23d(s, 0, o, 0, s, o));
}

cv::Point2d Registration::atlasFromImage(cv::Point2d imagePx) const {
    const cv::Point2d w = workingFromImage(imagePx);
    return apply(atlasFromWorking, w) + warp.at(w);
}

void Registration::atlasMaps(cv::Size size, cv::Mat& mapX, cv::Mat& mapY) const {
    // Evaluate on the working grid, then resize: the field is smooth, and this keeps an
    // 8000 x 5000 map at two resizes instead of 40 million bilinear look-ups.
    // A copy smaller than the working image is evaluated directly (its pixel (x, y) is working
    // pixel ((x + 0.5) sx - 0.5, ...), the cv::resize alignment); larger ones are resized from
    // the working grid below.
    const cv::Size full = workingGrey.size();
    const bool direct = size.width <= full.width && size.height <= full.height;
    const cv::Size ws = direct ? size : full;
    const double sx = double(full.width) / ws.width, sy = double(full.height) / ws.height;
    const cv::Matx23d workingFromOut(sx, 0, 0.5 * sx - 0.5, 0, sy, 0.5 * sy - 0.5);
    cv::Mat wx(ws, CV_32F), wy(ws, CV_32F);
    const bool hasWarp = !warp.empty();
    // The field is read as DisplacementField::at reads it (node positions clamped to the grid,
    // bilinear between nodes). The output's pixel x always reads the same two node columns with
    // the same weights, and its row y the same two node rows: both are tabled once, so each
    // pixel costs a few multiply-adds (cv::warpAffine did the same in 5 ms per component and
    // rounded the positions to 1/32 node).
    struct Tap {
        int i0, i1;
        float f;
    };
    const auto taps = [](int n, double scale, double offset, int nodes) {
        std::vector<Tap> out(static_cast<std::size_t>(n));
        for (int k = 0; k < n; ++k) {
            const double g = std::clamp(scale * k + offset, 0.0, double(nodes - 1));
            const int i0 = std::min(static_cast<int>(g), std::max(nodes - 2, 0));
            out[static_cast<std::size_t>(k)] = {i0, std::min(i0 + 1, nodes - 1), float(g - i0)};
        }
        return out;
    };
    std::vector<Tap> colTaps, rowTaps;
    if (hasWarp) {
        // Field nodes sit at multiples of cellPx: pixel (x, y) reads the field at its working
        // position / cellPx.
        const double inv = 1.0 / warp.cellPx();
        colTaps = taps(ws.width, inv * sx, inv * (0.5 * sx - 0.5), warp.dx().cols);
        rowTaps = taps(ws.height, inv * sy, inv * (0.5 * sy - 0.5), warp.dx().rows);
    }
    const cv::Matx23d t = compose(atlasFromWorking, workingFromOut);
    for (int y = 0; y < ws.height; ++y) {
        float* ox = wx.ptr<float>(y);
        float* oy = wy.ptr<float>(y);
        for (int x = 0; x < ws.width; ++x) {
            ox[x] = float(t(0, 0) * x + t(0, 1) * y + t(0, 2));
            oy[x] = float(t(1, 0) * x + t(1, 1) * y + t(1, 2));
        }
        if (hasWarp) {
            const Tap& r = rowTaps[static_cast<std::size_t>(y)];
            const float* x0 = warp.dx().ptr<float>(r.i0);
            const float* x1 = warp.dx().ptr<float>(r.i1);
            const float* y0 = warp.dy().ptr<float>(r.i0);
            const float* y1 = warp.dy().ptr<float>(r.i1);
            const float fy = r.f;
            for (int x = 0; x < ws.width; ++x) {
                const Tap& c = colTaps[static_cast<std::size_t>(x)];
                const float fx = c.f;
                ox[x] += (1 - fy) * ((1 - fx) * x0[c.i0] + fx * x0[c.i1]) +
                         fy * ((1 - fx) * x1[c.i0] + fx * x1[c.i1]);
                oy[x] += (1 - fy) * ((1 - fx) * y0[c.i0] + fx * y0[c.i1]) +
                         fy * ((1 - fx) * y1[c.i0] + fx * y1[c.i1]);
            }
        }
    }
    if (size == ws) {
        mapX = wx;
        mapY = wy;
        return;
    }
    cv::resize(wx, mapX, size, 0, 0, cv::INTER_LINEAR);
    cv::resize(wy, mapY, size, 0, 0, cv::INTER_LINEAR);
}

cv::Mat Registration::warpedLabels(const cv::Mat& atlasLabels, cv::Size size) const {
    CV_Assert(atlasLabels.type() == CV_32S);
    cv::Mat mx, my, out;
    atlasMaps(size, mx, my);
    // remap has no 32S support; labels go through as float bit patterns untouched by NEAREST.
    cv::Mat asFloat(atlasLabels.size(), CV_32F, atlasLabels.data, atlasLabels.step);
    cv::remap(asFloat, out, mx, my, cv::INTER_NEAREST, cv::BORDER_CONSTANT, cv::Scalar(0));
    return cv::Mat(out.size(), CV_32S, out.data, out.step).clone();
}

namespace {
/// The field options of the intensity and the region warp are usable (the rule the error names).
bool warpOptionsValid(const IntensityWarpOptions& w) {
    return w.gridMaxSide >= 32 && !w.levels.empty() && w.stiffness >= 0 && w.damping >= 0 &&
           w.robustK > 0 && w.maxStepGridPx > 0 && w.holdOutBlockPx >= 0 &&
           w.localSigmaGridPx >= 0 &&
           std::all_of(w.levels.begin(), w.levels.end(), [](const IntensityWarpLevel& l) {
               return l.spacingGridPx >= 4 && l.imageSigma >= 0 && l.iterations >= 0;
           });
}

/// Measures every gap's (Tear, Missing; polygons in full-resolution px) mirroredShare of the
/// section's glass and every fragment's of its tissue, and with
/// DamageParams::leaveOutMirroredGaps removes those reaching DamageParams::mirroredGap: anatomy
/// on both sides, not damage. The section's tissue and glass are
/// carried into atlas px by the registration's map of the working pixels (an atlas px is glass when
/// most working pixels landing on it are), the glass grown by the registration slack.
void dropMirroredGaps(std::vector<DamageRegion>& regions, const Registration& reg,
                      const cv::Mat& tissue, const cv::Mat& atlasMask, double brainWidth,
                      const DamageParams& params) {
    const cv::Moments am = cv::moments(atlasMask, true);
    const auto gapOrPiece = [](const DamageRegion& d) {
        return isGap(d) || d.kind == DamageKind::Fragment;
    };
    const bool anyGap = std::any_of(regions.begin(), regions.end(), gapOrPiece);
    if (am.m00 <= 0 || !anyGap)
        return;
    const double midlineX = am.m10 / am.m00;
    cv::Mat ax, ay;
    reg.atlasMaps(tissue.size(), ax, ay);
    cv::Mat seen = cv::Mat::zeros(atlasMask.size(), CV_32S), glassCount = seen.clone();
    const cv::Rect inAtlas(0, 0, atlasMask.cols, atlasMask.rows);
    for (int y = 0; y < tissue.rows; ++y) {
        const float* px = ax.ptr<float>(y);
        const float* py = ay.ptr<float>(y);
        const std::uint8_t* t = tissue.ptr<std::uint8_t>(y);
        for (int x = 0; x < tissue.cols; ++x) {
            const cv::Point a(cvRound(px[x]), cvRound(py[x]));
            if (!inAtlas.contains(a))
                continue;
            ++seen.at<std::int32_t>(a);
            glassCount.at<std::int32_t>(a) += t[x] == 0;
        }
    }
    const cv::Mat known = seen > 0;
    cv::Mat glass = (2 * glassCount > seen) & known;
    const cv::Mat tissueSeen = known & ~glass;
    const cv::Matx22d l(reg.atlasFromWorking(0, 0), reg.atlasFromWorking(0, 1),
                        reg.atlasFromWorking(1, 0), reg.atlasFromWorking(1, 1));
    const double atlasPerWorking = std::sqrt(std::abs(cv::determinant(l)));
    const int slack =
        std::max(1, static_cast<int>(std::lround(params.slackFrac * brainWidth * atlasPerWorking)));
    cv::dilate(
        glass, glass,
        cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * slack + 1, 2 * slack + 1)));
    const double s = reg.workingScale;
    std::vector<DamageRegion> kept;
    for (DamageRegion& d : regions) {
        if (gapOrPiece(d)) {
            const std::vector<cv::Point> poly = pixelPolygon(d.polygon, s);
            // The gap in its box (the maps cut alike), not on the whole image.
            const cv::Rect box = poly.empty() ? cv::Rect()
                                              : (cv::boundingRect(poly) + cv::Size(1, 1)) &
                                                    cv::Rect(0, 0, tissue.cols, tissue.rows);
            if (poly.size() >= 3 && box.area() > 0) {
                const cv::Mat mask = polygonMask(poly, box);
                const cv::Mat bx = ax(box), by = ay(box);
                // A gap's twin shows glass; a piece lying apart has a twin of tissue (the
                // other side's cortex apart from the brain stem, caudally).
                const bool piece = d.kind == DamageKind::Fragment;
                d.mirrorShare =
                    mirroredShare(mask, bx, by, midlineX, piece ? tissueSeen : glass, known, slack);
                if (params.leaveOutMirroredGaps && d.mirrorShare >= params.mirroredGap)
                    continue;
            }
        }
        kept.push_back(std::move(d));
    }
    regions = std::move(kept);
}
} // namespace

core::Result<Registration> registerSection(const cv::Mat& section, const cv::Mat& atlasLabels,
                                           const RegistrationOptions& options) {
    if (atlasLabels.empty() || atlasLabels.type() != CV_32S)
        return makeError(ErrorCode::InvalidArgument,
                         "atlas labels must be a non-empty CV_32S image");
    if (options.workingMaxSide < 128)
        return makeError(ErrorCode::InvalidArgument, "working size must be at least 128 px");
    if (options.imageUmPerPx < 0 || options.atlasUmPerPx < 0)
        return makeError(ErrorCode::InvalidArgument, "pixel sizes must be positive");
    if (!(options.maxTurnDeg >= 0 && options.maxTurnDeg <= 180))
        return makeError(ErrorCode::InvalidArgument,
                         "the largest turn of a section on the slide must be 0 to 180 degrees");
    if (options.smoothWarp && !(options.smooth.nodeSpacing > 0 && options.smooth.stiffness >= 0 &&
                                options.smooth.robustK > 0))
        return makeError(ErrorCode::InvalidArgument,
                         "smooth warp options: node spacing and robustness must be positive, "
                         "stiffness not negative");
    if (!options.atlasIntensity.empty() && (options.atlasIntensity.type() != CV_32F ||
                                            options.atlasIntensity.size() != atlasLabels.size()))
        return makeError(ErrorCode::InvalidArgument,
                         "atlas intensity must be CV_32F and the size of the atlas labels");
    // With an atlas intensity plane the dense refinement takes its own options, and those
    // without one when the plane is set aside as not the section's stain: both are checked.
    const auto badDense = [](const DenseRefineOptions& d) {
        return d.gridMaxSide < 32 || d.levels.empty() || d.fieldSigma < 0 || d.damping < 0 ||
               std::any_of(d.levels.begin(), d.levels.end(), [](const DenseLevel& l) {
                   return l.imageSigma < 0 || l.window < 1 || l.iterations < 0;
               });
    };
    if (options.denseRefine && (badDense(options.dense) || (!options.atlasIntensity.empty() &&
                                                            badDense(options.denseWithIntensity))))
        return makeError(ErrorCode::InvalidArgument,
                         "dense refinement options: grid at least 32 px, at least one level, "
                         "windows at least 1, no negative sigma, damping or iterations");
    if (options.intensityAffine &&
        (options.intensity.gridMaxSide < 32 || options.intensity.levelSigmas.empty() ||
         options.intensity.iterations < 0 || !(options.intensity.robustK > 0) ||
         !(options.intensity.damping >= 0) || !(options.intensity.maxStepGridPx > 0) ||
         options.intensity.holdOutBlockPx < 0 ||
         std::any_of(options.intensity.levelSigmas.begin(), options.intensity.levelSigmas.end(),
                     [](double sigma) { return !(sigma >= 0); })))
        return makeError(ErrorCode::InvalidArgument,
                         "intensity affine options: grid at least 32 px, at least one level, no "
                         "negative sigma, iterations, damping or block size, positive robustness "
                         "and step");
    // The intensity and the region warp fit the same field: one check, named for each.
    constexpr const char* kWarpRule =
        " options: grid at least 32 px, at least one level, control spacing at least 4 px, no "
        "negative sigma, iterations, stiffness, damping or block size, positive robustness and "
        "step";
    if (options.intensityWarp && !warpOptionsValid(options.intensityWarpOptions))
        return makeError(ErrorCode::InvalidArgument, std::string("intensity warp") + kWarpRule);
    if (options.regionWarp && !warpOptionsValid(options.regionWarpOptions.warp))
        return makeError(ErrorCode::InvalidArgument, std::string("region warp") + kWarpRule);
    if (!options.regionLabels.empty() && (options.regionLabels.type() != CV_32S ||
                                          options.regionLabels.size() != atlasLabels.size()))
        return makeError(ErrorCode::InvalidArgument,
                         "region labels must be 32-bit integer labels of the atlas slice's size");
    const cv::Mat atlasMask = atlasLabels != 0;
    if (cv::countNonZero(atlasMask) < 16)
        return makeError(ErrorCode::InvalidArgument, "atlas slice has no labelled brain");

    Registration reg;
    StepTimer timer(reg.timingsMs, reg.cpuMs, options.progress);
    auto prepared = prepareSection(section, options.workingMaxSide);
    if (!prepared)
        return prepared.error();
    reg.imageSize = section.size();
    reg.workingScale = prepared->scale;
    reg.contrast = prepared->contrast;
    reg.workingGrey = prepared->grey;
    reg.workingTissueMask = prepared->tissueMask;
    timer.lap("prepare");

    // Section edges (MEI): only where tissue is, not on debris, and not where excluded. Nothing
    // before the edge points needs them: they are found beside the placement search below.
    const int grow = std::max(2, static_cast<int>(std::lround(reg.workingGrey.cols / 200.0)));
    cv::Mat mei;
    double edgesWallMs = 0, edgesCpuMs = 0;
    const auto findEdges = [&] {
        const auto start = Clock::now();
        const double cpuStart = threadCpuMs();
        mei = dominantEdges(reg.workingGrey, options.edges);
        cv::Mat near;
        cv::dilate(
            reg.workingTissueMask, near,
            cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * grow + 1, 2 * grow + 1)));
        mei &= near;
        if (!options.excludeMask.empty()) {
            cv::Mat ex;
            cv::resize(options.excludeMask != 0, ex, reg.workingGrey.size(), 0, 0,
                       cv::INTER_NEAREST);
            mei.setTo(0, ex);
        }
        edgesWallMs = std::chrono::duration<double, std::milli>(Clock::now() - start).count();
        edgesCpuMs = threadCpuMs() - cpuStart;
    };

    // Detached fragments (more tissue pieces than the atlas brain has) would pull the outline,
    // the overlap and the edges: the placement uses the main pieces only.
    const cv::Mat fragments = options.detectDamage ? extraPieces(fillHoles(reg.workingTissueMask),
                                                                 atlasMask, kMinFragmentShare)
                                                   : cv::Mat();
    cv::Mat mainTissue = reg.workingTissueMask;
    cv::Mat nearFragments; // the edges here are the fragments', not the placed tissue's
    if (!fragments.empty()) {
        mainTissue = reg.workingTissueMask & ~fragments;
        cv::dilate(
            fragments, nearFragments,
            cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * grow + 1, 2 * grow + 1)));
    }
    // The fragments are damage detection's share of this step.
    timer.lap("damage-fragments", false);
    const cv::Mat tissueFilled = fillHoles(mainTissue);
    const auto tissueSamples = outerContourPoints(tissueFilled);
    const auto atlasOutline = outerContourPoints(atlasMask);
    const OrientedBox imgBox = orientedBox(tissueSamples);
    const OrientedBox atlBox = orientedBox(atlasOutline);
    if (imgBox.halfMajor <= 0 || atlBox.halfMajor <= 0)
        return makeError(ErrorCode::NoTissue, "no tissue found: the tissue outline is degenerate");
    const double knownScale = options.imageUmPerPx > 0 && options.atlasUmPerPx > 0
                                  ? options.imageUmPerPx / (options.atlasUmPerPx * reg.workingScale)
                                  : 0.0;
    const double scaleGuess = knownScale > 0
                                  ? knownScale
                                  : std::sqrt(atlBox.halfMajor * atlBox.halfMinor /
                                              std::max(imgBox.halfMajor * imgBox.halfMinor, 1e-9));

    // Feature density: the same spacing on both sides, measured in atlas pixels.
    const double atlasH = std::max(atlBox.halfMajor, atlBox.halfMinor) * 2 * 0.7;
    const double spacingAtlas = std::max(0.75, atlasH / 300.0);
    const double spacingImg = spacingAtlas / scaleGuess;
    reg.atlasEdges = mlsEdgePoints(labelBoundarySamples(atlasLabels), float(spacingAtlas),
                                   float(3 * spacingAtlas));
    const EdgePoints atlasOuter =
        mlsEdgePoints(atlasOutline, float(spacingAtlas), float(3 * spacingAtlas));
    const EdgePoints imgOuter =
        mlsEdgePoints(tissueSamples, float(spacingImg), float(std::max(2.0, 3 * spacingImg)));
    if (imgOuter.size() < 20)
        return makeError(ErrorCode::NoTissue, "no tissue found: the tissue outline is too small");
    const PointGrid atlasGrid(reg.atlasEdges.points, float(atlasH / 40));
    timer.lap("features");

    // Candidate placements: the OBB leaves the axis signs (and, for roundish shapes, which axis
    // is which) open. Each candidate is refined on the outlines and scored by overlap.
    struct Candidate {
        double sMaj, sMin;
        bool swap;
    };
    std::vector<Candidate> cands{{1, 1, false}, {-1, -1, false}};
    if (options.allowMirror)
        cands.insert(cands.end(), {{1, -1, false}, {-1, 1, false}});
    const double aspectImg = imgBox.halfMajor / std::max(imgBox.halfMinor, 1e-9);
    const double aspectAtl = atlBox.halfMajor / std::max(atlBox.halfMinor, 1e-9);
    if (aspectImg < 1.25 || aspectAtl < 1.25) {
        const size_t n = cands.size();
        for (size_t i = 0; i < n; ++i)
            cands.push_back({cands[i].sMaj, -cands[i].sMin, true});
    }
    const std::vector<IcpLevel> coarse{
        {30, atlasH / 5}, {20, atlasH / 8}, {15, atlasH / 12}, {10, atlasH / 20}};
    struct Placed {
        cv::Matx23d init, t;
        double overlap;
    };
    std::vector<Placed> placed;
    std::vector<cv::Matx23d> inits;
    for (const Candidate& c : cands)
        inits.push_back(obbPlacement(imgBox, atlBox, c.sMaj, c.sMin, c.swap, knownScale));
    const OverlapScorer scorer(tissueFilled, atlasMask);
    if (aspectImg < 1.25 || aspectAtl < 1.25) {
        // A roundish outline leaves the OBB's axes to chance: rotations every 15 degrees, scored
        // by overlap, add the two best (at least 45 degrees apart) as starting points.
        std::vector<std::pair<double, int>> sweep;
        for (int deg = 0; deg < 360; deg += 15)
            sweep.emplace_back(scorer(rotatedPlacement(imgBox, atlBox, deg, scaleGuess)), deg);
        std::sort(sweep.rbegin(), sweep.rend());
        std::vector<int> picked;
        for (const auto& candidate : sweep) {
            const int deg =
                candidate.second; // a plain local: clang 14 cannot capture a structured binding
            const bool apart = std::all_of(picked.begin(), picked.end(), [&](int other) {
                const int d = std::abs(deg - other) % 360;
                return std::min(d, 360 - d) >= 45;
            });
            if (!apart)
                continue;
            picked.push_back(deg);
            inits.push_back(rotatedPlacement(imgBox, atlBox, deg, scaleGuess));
            if (picked.size() == 3)
                break;
        }
    }
    // The thin cracks' grey image, at full resolution up to crackMaxSidePx (damage detection
    // at the end): it needs only the section.
    const int longSide = std::max(section.cols, section.rows);
    const double crackScale = longSide > options.damage.crackMaxSidePx
                                  ? double(options.damage.crackMaxSidePx) / longSide
                                  : 1.0;
    const cv::Size crackSize = crackScale < 1
                                   ? cv::Size(std::max(1, cvRound(section.cols * crackScale)),
                                              std::max(1, cvRound(section.rows * crackScale)))
                                   : section.size();
    std::optional<cv::Mat> crackGrey;
    const auto makeCrackGrey = [&] {
        cv::Mat crackSection = section;
        if (crackScale < 1)
            cv::resize(section, crackSection, crackSize, 0, 0, cv::INTER_AREA);
        if (auto full = toGreyFloat(crackSection); full) {
            crackGrey = reg.contrast == Contrast::Brightfield ? cv::Mat(-*full) : *full;
        }
    };
    // Each starting placement is refined on the outlines, side by side with the others, with the
    // section's edges (task 0) and with the cracks' grey image (task 1).
    placed.resize(inits.size());
    runTasks(int(inits.size()) + 2, [&](int task) {
        if (task == 0) {
            findEdges();
            return;
        }
        if (task == 1) {
            if (options.detectDamage)
                makeCrackGrey();
            return;
        }
        const cv::Matx23d& init = inits[size_t(task - 2)];
        const IcpResult r = multiLevelIcp(imgOuter, atlasOuter, init, coarse, 6, scaleGuess);
        // The refinement can wander off on an odd outline; the placement it started from stays
        // in the running, and the overlap search polishes whichever is better.
        const double fromIcp = scorer(r.targetFromSource), fromInit = scorer(init);
        placed[size_t(task - 2)] = {init, fromIcp >= fromInit ? r.targetFromSource : init,
                                    std::max(fromIcp, fromInit)};
    });
    // The lab's mounting rule: a placement turned further than it allows.
    const auto turnedTooFar = [&](const Placed& p) {
        return options.maxTurnDeg < 180 && std::abs(turnDegrees(p.t)) > options.maxTurnDeg;
    };
    // The overlap search polishes the placements that start near the best one (among those the
    // mounting rule allows, when any does; the rule is applied below); one that starts further
    // behind keeps its start and its overlap, and so cannot be chosen or be a close call.
    {
        const bool anyAllowed = !std::all_of(placed.begin(), placed.end(), turnedTooFar);
        double lead = 0;
        for (const Placed& p : placed)
            if (!anyAllowed || !turnedTooFar(p))
                lead = std::max(lead, p.overlap);
        std::vector<size_t> polish;
        for (size_t k = 0; k < placed.size(); ++k)
            if (placed[k].overlap >= lead - kPolishBehind)
                polish.push_back(k);
        runTasks(int(polish.size()), [&](int i) {
            Placed& p = placed[polish[size_t(i)]];
            p.t = refineByOverlap(scorer, p.t, imgBox.centre, 2 * imgBox.halfMajor, p.overlap);
        });
    }
    if (!nearFragments.empty())
        mei.setTo(0, nearFragments);
    std::sort(placed.begin(), placed.end(),
              [](const Placed& a, const Placed& b) { return a.overlap > b.overlap; });
    // Placements the mounting rule does not allow are dropped, unless none is allowed.
    if (!std::all_of(placed.begin(), placed.end(), turnedTooFar))
        placed.erase(std::remove_if(placed.begin(), placed.end(), turnedTooFar), placed.end());
    // Starts that the outline search brought to the same place (the section box's four ends
    // within kSamePlaceAtlasPx of a better placement's) are one placement: the full ICP from
    // each would end in the same basin, so only the better one is kept as a close call.
    {
        const std::array<cv::Point2d, 4> ends{
            cv::Point2d(imgBox.centre) + imgBox.halfMajor * cv::Point2d(imgBox.major),
            cv::Point2d(imgBox.centre) - imgBox.halfMajor * cv::Point2d(imgBox.major),
            cv::Point2d(imgBox.centre) + imgBox.halfMinor * cv::Point2d(imgBox.minor),
            cv::Point2d(imgBox.centre) - imgBox.halfMinor * cv::Point2d(imgBox.minor)};
        const auto samePlace = [&](const Placed& a, const Placed& b) {
            return std::all_of(ends.begin(), ends.end(), [&](const cv::Point2d& e) {
                return cv::norm(apply(a.t, e) - apply(b.t, e)) <= kSamePlaceAtlasPx;
            });
        };
        std::vector<Placed> distinct;
        for (const Placed& p : placed)
            if (std::none_of(distinct.begin(), distinct.end(),
                             [&](const Placed& q) { return samePlace(p, q); }))
                distinct.push_back(p);
        placed = std::move(distinct);
    }
    const cv::Matx23d bestInit = placed.front().init;
    const cv::Matx23d best = placed.front().t;
    reg.stageAffines.emplace_back("obb", bestInit);
    reg.stageAffines.emplace_back("outline", best);
    timer.lap("initialise");
    timer.record("edges", edgesWallMs, edgesCpuMs);

    // Algorithm 2: deep, asymmetric concavities of the outline are damage; their edges stay out
    // of the matching. The mirror is the atlas midline seen through the initial placement.
    const double brainWidth = 2 * imgBox.halfMajor;
    reg.brainWidthPx = brainWidth / reg.workingScale;
    cv::Mat damagedOutline; // where the outline is a deep asymmetric concavity
    if (options.detectDamage) {
        const Outline outline = tissueOutline(mainTissue);
        reg.concavities = deepConcavities(outline, options.damage.alphaFrac * brainWidth);
        const cv::Moments am = cv::moments(atlasMask, true);
        const double midline = am.m00 > 0 ? am.m10 / am.m00 : atlasLabels.cols / 2.0;
        const cv::Matx23d flip(-1, 0, 2 * midline, 0, 1, 0);
        const cv::Matx23d mirror = compose(invert(best), compose(flip, best));
        markSymmetric(reg.concavities, outline, mirror, brainWidth, options.damage);
        damagedOutline = concavityExclusion(reg.concavities, mei.size(), 0.02 * brainWidth);
        mei.setTo(0, damagedOutline);
    }
    // Algorithm 2's share of the time apart from the edge points every registration needs
    // (not a step of the progress count: that stays the same with or without damage).
    timer.lap("damage-outline", false);
    reg.sectionEdges =
        mlsEdgePoints(edgePixels(mei), float(spacingImg), float(std::max(2.0, 3 * spacingImg)));
    if (reg.sectionEdges.size() < 20)
        return makeError(ErrorCode::NoTissue, "no tissue found: too few tissue edges to register");
    timer.lap("edge-points");

    // Global alignment with every edge, thresholds tightened as in the paper's implementation
    // section: 10, 8, 6, 4 degrees and H/10 .. H/80.
    const std::vector<IcpLevel> fine{
        {10, atlasH / 10}, {8, atlasH / 20}, {6, atlasH / 40}, {4, atlasH / 80}};
    // An outline alone can fit nearly as well upside down (a roundish section, a piece missing):
    // close calls are settled after the full ICP by the internal edges and the outline together.
    auto edgeAgreement = [&](const cv::Matx23d& t) {
        std::vector<cv::Point2f> mapped;
        mapped.reserve(reg.sectionEdges.size());
        for (const auto& p : reg.sectionEdges.points)
            mapped.emplace_back(apply(t, p));
        return shareMatched(mapped, atlasGrid, atlasH / 80);
    };
    // The full ICP from the best placement and from each close one (within 0.05 of its
    // overlap), side by side, level by level; before the finest level (the most points and
    // iterations) the close ones whose edge agreement already trails are dropped; which of the
    // rest is kept is settled in order below.
    size_t close = 1;
    while (close < placed.size() && placed[close].overlap >= placed.front().overlap - 0.05)
        ++close;
    std::vector<IcpResult> fromPlaced(close);
    std::vector<size_t> running(close);
    for (size_t k = 0; k < close; ++k) {
        fromPlaced[k].targetFromSource = placed[k].t;
        running[k] = k;
    }
    for (size_t level = 0; level < fine.size(); ++level) {
        if (level + 1 == fine.size() && running.size() > 1) {
            std::vector<double> a(running.size());
            for (size_t i = 0; i < running.size(); ++i)
                a[i] = edgeAgreement(fromPlaced[running[i]].targetFromSource);
            const double lead = *std::max_element(a.begin(), a.end());
            std::vector<size_t> kept;
            for (size_t i = 0; i < running.size(); ++i)
                if (a[i] >= lead - kTrailingAgreement)
                    kept.push_back(running[i]);
            running = std::move(kept);
        }
        runTasks(int(running.size()), [&](int i) {
            IcpResult& r = fromPlaced[running[size_t(i)]];
            r = multiLevelIcp(reg.sectionEdges, reg.atlasEdges, r.targetFromSource, {fine[level]},
                              8, scaleGuess);
        });
    }
    IcpResult affine = std::move(fromPlaced[running.front()]);
    // Which of the close placements is kept: the one that leaves the least unexplained, by the
    // product of what the section's edges leave unmatched (1 - edge agreement) and what the
    // outline leaves outside the atlas brain (1 - polished overlap). Each measure counts by its
    // relative change, so the outline, whose misfit is a few per cent of the brain and grows by
    // a third or more upside down, is heard beside the edges, which on real tissue (texture,
    // tile seams) match the atlas about as well either way up (docs/registration.md, "Which
    // way up: the least misfit of outline and edges"). Products within 1% are a tie, settled
    // by how well the atlas regions, each painted at one fitted level, explain the section's own
    // contrast under each affine (the dense measure, on a 128 px copy): a tie that
    // floating-point differences between compilers could flip is decided by a second,
    // independent measure instead.
    constexpr double kMisfitTie = 0.01; // in the log of the product
    const auto misfit = [](double agreement, double overlap) {
        return std::log(std::max(1e-9, 1 - agreement)) + std::log(std::max(1e-9, 1 - overlap));
    };
    cv::Mat tieGrey, tieWeight;
    auto regionFit = [&](const cv::Matx23d& t) {
        const cv::Size ws = reg.workingGrey.size();
        const double f = std::min(1.0, 128.0 / std::max(ws.width, ws.height));
        const cv::Size gs(std::max(8, static_cast<int>(std::lround(ws.width * f))),
                          std::max(8, static_cast<int>(std::lround(ws.height * f))));
        if (tieGrey.empty()) {
            cv::resize(reg.workingGrey, tieGrey, gs, 0, 0, cv::INTER_AREA);
            cv::resize(tissueFilled, tieWeight, gs, 0, 0, cv::INTER_AREA);
            tieWeight = tieWeight > 127;
            cv::dilate(tieWeight, tieWeight, cv::Mat());
        }
        const double sx = double(ws.width) / gs.width, sy = double(ws.height) / gs.height;
        const cv::Matx23d m = compose(t, cv::Matx23d(sx, 0, 0.5 * sx - 0.5, 0, sy, 0.5 * sy - 0.5));
        cv::Mat mx(gs, CV_32F), my(gs, CV_32F);
        for (int y = 0; y < gs.height; ++y)
            for (int x = 0; x < gs.width; ++x) {
                mx.at<float>(y, x) = float(m(0, 0) * x + m(0, 1) * y + m(0, 2));
                my.at<float>(y, x) = float(m(1, 0) * x + m(1, 1) * y + m(1, 2));
            }
        DenseRefineOptions measureOnly;
        measureOnly.levels = {{1.0, 4, 0}};
        measureOnly.holdOutBlockPx = 0;
        measureOnly.biasSigma = 0;
        return refineDense(tieGrey, tieWeight, mx, my, atlasLabels, cv::Mat(), measureOnly)
            .explainedBefore;
    };
    double agreement = edgeAgreement(affine.targetFromSource);
    double fitOfBest = std::numeric_limits<double>::quiet_NaN();
    size_t chosen = running.front(); // the placement `affine` came from
    for (size_t i = 1; i < running.size(); ++i) {
        const size_t k = running[i];
        IcpResult& other = fromPlaced[k];
        const double a = edgeAgreement(other.targetFromSource);
        const double gain =
            misfit(agreement, placed[chosen].overlap) - misfit(a, placed[k].overlap);
        bool better = gain > kMisfitTie;
        double fit = std::numeric_limits<double>::quiet_NaN();
        if (std::abs(gain) <= kMisfitTie) {
            if (std::isnan(fitOfBest))
                fitOfBest = regionFit(affine.targetFromSource);
            fit = regionFit(other.targetFromSource);
            better = fit > fitOfBest;
        }
        if (better) {
            agreement = a;
            affine = std::move(other);
            chosen = k;
            fitOfBest = fit;
        }
    }
    reg.atlasFromWorking = affine.targetFromSource;
    reg.quality.residualAffine = affine.rmsResidual;
    reg.stageAffines.emplace_back("icp", reg.atlasFromWorking);
    // With an atlas intensity plane (a template-like stain), the edge-based affine is polished
    // against the plane over the tissue, damage left out (intensity_affine.hpp); kept only when
    // it explains more of the section on held-out blocks.
    cv::Mat plane = options.atlasIntensity; // set aside when it is not the section's stain
    if (options.intensityAffine && !plane.empty()) {
        const cv::Size ws = reg.workingGrey.size();
        const cv::Size gs = gridSize(ws, options.intensity.gridMaxSide);
        cv::Mat grey;
        cv::resize(reg.workingGrey, grey, gs, 0, 0, cv::INTER_AREA);
        const cv::Mat weight =
            measuredArea(gs, tissueFilled, options.excludeMask, fragments, damagedOutline);
        const double sx = double(ws.width) / gs.width, sy = double(ws.height) / gs.height;
        const cv::Matx23d workingFromGrid(sx, 0, 0.5 * sx - 0.5, 0, sy, 0.5 * sy - 0.5);
        const IntensityAffine ia = refineAffineByIntensity(
            grey, weight, compose(reg.atlasFromWorking, workingFromGrid), plane, options.intensity);
        reg.quality.intensityExplainedBefore = ia.explainedBefore;
        reg.quality.intensityExplainedAfter = ia.explainedAfter;
        reg.quality.intensityAffineKept = ia.accepted;
        if (ia.accepted) {
            reg.atlasFromWorking = compose(ia.atlasFromGrid, invert(workingFromGrid));
            reg.stageAffines.emplace_back("intensity", reg.atlasFromWorking);
        }
        // A plane that does not explain most of the section is not its stain (an immunostain
        // against the average template): the later stages run as without one.
        if (!ia.planeIsTheStain)
            plane = cv::Mat();
    }
    reg.quality.intensityPlaneUsed = !plane.empty();
    const DenseRefineOptions& denseOptions =
        plane.empty() ? options.dense : options.denseWithIntensity;
    // Through the affine alone: the warp leaves it as it is. It also decides the outline pull.
    reg.quality.tissueOverlap = overlap(tissueFilled, atlasMask, reg.atlasFromWorking);
    timer.lap("icp");

    // Non-linear: tight correspondences become Dirichlet conditions of Laplace's equation; a few
    // rounds let the warp bring in matches the affine left outside the thresholds.
    const double finalDist = atlasH / 60;
    // The non-linear stages (edge warps, intensity or region warp, dense refinement, fold
    // repair) on the affine, with or without the edge warps and the smooth stage; `timed` laps
    // each step; `result` false (the damage map's chain) leaves out the dense refinement's
    // confidence, which only the result's map keeps. Without the edge warps, when the region
    // warp runs, the dense refinement measures the fine regions (and by default only measures:
    // RegistrationOptions::refineAfterRegionWarp).
    const bool regionWarpRuns =
        options.regionWarp && plane.empty() && !options.regionLabels.empty();
    const bool edgeWarps =
        options.nonLinear && (options.edgeWarpAfterIntensity || !reg.quality.intensityAffineKept);
    const auto nonLinearStages = [&](Registration& r, bool edges, bool smooth, bool timed,
                                     bool result) {
        const auto lap = [&](const char* name) {
            if (timed)
                timer.lap(name);
        };
        // The field stages' inputs: the section, its measured area and the map on a grid of
        // `maxSide`.
        struct GridInputs {
            cv::Size ws, gs;
            cv::Mat grey, weight, mx, my;
        };
        const auto gridInputs = [&](int maxSide) {
            GridInputs g;
            g.ws = r.workingGrey.size();
            g.gs = gridSize(g.ws, maxSide);
            cv::resize(r.workingGrey, g.grey, g.gs, 0, 0, cv::INTER_AREA);
            g.weight =
                measuredArea(g.gs, tissueFilled, options.excludeMask, fragments, damagedOutline);
            r.atlasMaps(g.gs, g.mx, g.my);
            return g;
        };
        // An intensity or region warp's held-out shares into the quality; its field into the
        // map when kept.
        const auto keepField = [&](const IntensityWarp& w, cv::Size ws, double& before,
                                   double& after, bool& kept) {
            before = w.explainedBefore;
            after = w.explainedAfter;
            kept = w.accepted;
            if (w.accepted)
                r.warp = addToWarp(r.warp, ws, w.ux, w.uy);
        };
        if (edges) {
            LaplaceOptions lo;
            lo.cellPx = std::max(2.0, std::max(r.workingGrey.cols, r.workingGrey.rows) / 200.0);
            // Point-to-line targets: an edge only says where the boundary is across it, so the
            // warp is pulled across edges and Laplace's equation carries the rest.
            const std::vector<std::pair<double, double>> rounds{
                {atlasH / 30, 8}, {atlasH / 40, 6}, {atlasH / 50, 5}, {finalDist, 5}};
            // A section far from its plane's shape (parts shifted apart, the bulbs' or hind
            // brain's outline changing fast along the cutting axis) keeps a misfit outline that no
            // edge pair reaches, and the misfit reads as missing tissue. Then the tissue outline
            // (outside the damaged concavities) is also paired with the atlas outline, one boundary
            // each, so further away than edges among edges.
            const bool pullOutline = r.quality.tissueOverlap < options.outlinePullBelowOverlap;
            // The tissue outline outside the damaged concavities: the outline pull's and the
            // smooth stage's pairs.
            EdgePoints outline;
            for (size_t i = 0; (pullOutline || smooth) && i < imgOuter.size(); ++i) {
                const cv::Point p(std::clamp(cvRound(imgOuter.points[i].x), 0, mei.cols - 1),
                                  std::clamp(cvRound(imgOuter.points[i].y), 0, mei.rows - 1));
                if (!damagedOutline.empty() && damagedOutline.at<std::uint8_t>(p))
                    continue;
                outline.points.push_back(imgOuter.points[i]);
                outline.normals.push_back(imgOuter.normals[i]);
            }
            const double outlineReach = atlasH * options.outlinePullReach;
            const PointGrid atlasOuterGrid(atlasOuter.points, float(outlineReach / 2));
            // The smooth stage: a B-spline field fitted to the edges and the tissue outline
            // (outside damaged concavities) at once; the Laplace warp then adds local corrections.
            DisplacementField base;
            if (smooth) {
                const PointGrid outerGrid(atlasOuter.points, float(atlasH / 40));
                SmoothWarpOptions so = options.smooth;
                if (so.levels.empty())
                    so.levels = {{atlasH / 15, 20, 3}, {atlasH / 25, 15, 3}, {atlasH / 40, 10, 3}};
                const SmoothWarp sw =
                    fitSmoothWarp(r.workingGrey.size(), r.atlasFromWorking,
                                  {{&r.sectionEdges, &r.atlasEdges, &atlasGrid, 1.0},
                                   {&outline, &atlasOuter, &outerGrid, 1.0}},
                                  lo.cellPx, so);
                base = sw.field;
                r.warp = base;
                r.quality.smoothBefore = sw.rmsBefore;
                r.quality.smoothAfter = sw.rmsAfter;
                r.quality.smoothMatches = sw.matches;
            }
            std::vector<cv::Point2d> pts, disp;
            for (size_t round = 0; round < rounds.size(); ++round) {
                const auto [dist, ang] = rounds[round];
                pts.clear();
                disp.clear();
                addWarpConditions(r.sectionEdges, r.atlasFromWorking, r.warp, r.atlasEdges,
                                  atlasGrid, dist, ang, pts, disp);
                if (pts.size() < 12)
                    break;
                if (pullOutline)
                    addWarpConditions(outline, r.atlasFromWorking, r.warp, atlasOuter,
                                      atlasOuterGrid, std::max(dist, outlineReach), 15, pts, disp);
                // The Laplace warp interpolates what the smooth field leaves at the conditions.
                for (size_t k = 0; k < pts.size(); ++k)
                    disp[k] -= base.at(pts[k]);
                // The rounds before the last only choose the next round's matches: their
                // solution needs fewer sweeps than the field that is kept.
                LaplaceOptions lr = lo;
                if (round + 1 < rounds.size())
                    lr.sweepsPerLevel = kLaplaceSweepsBeforeLastRound;
                r.warp = addFields(solveLaplaceWarp(r.workingGrey.size(), pts, disp, lr), base);
            }
        }
        lap("warp");

        // With an atlas intensity plane, a smooth field so that the section and the plane agree
        // inside the tissue (intensity_warp.hpp): the non-affine part the intensity affine leaves.
        if (options.intensityWarp && !plane.empty()) {
            const GridInputs g = gridInputs(options.intensityWarpOptions.gridMaxSide);
            const IntensityWarp iw = refineWarpByIntensity(g.grey, g.weight, g.mx, g.my, plane,
                                                           options.intensityWarpOptions);
            keepField(iw, g.ws, r.quality.intensityWarpExplainedBefore,
                      r.quality.intensityWarpExplainedAfter, r.quality.intensityWarpKept);
            lap("iwarp");
        }
        // Without a plane, the same field against the fine atlas regions painted with the section's
        // own levels (any stain: each region is roughly homogeneous).
        if (regionWarpRuns) {
            const GridInputs g = gridInputs(options.regionWarpOptions.warp.gridMaxSide);
            const IntensityWarp rw =
                refineWarpByRegions(g.grey, g.weight, g.mx, g.my, options.regionLabels,
                                    options.regionWarpOptions.glassIds, options.regionWarpOptions);
            keepField(rw, g.ws, r.quality.regionWarpExplainedBefore,
                      r.quality.regionWarpExplainedAfter, r.quality.regionWarpKept);
            r.quality.regionWarpLeftOut = rw.leftOut;
            lap("rwarp");
        }

        // Dense refinement (beyond the paper): the atlas regions are fitted to the section's own
        // contrast inside the tissue on a reduced grid; damaged and excluded parts stay out.
        // After the region warp in the result's map it only measures (the confidence): the
        // region warp has fitted the same regions with a richer model, and moving the map again
        // made it no better (RegistrationOptions::refineAfterRegionWarp).
        if (options.denseRefine) {
            const GridInputs g = gridInputs(denseOptions.gridMaxSide);
            // After the region warp, against the fine regions it fitted.
            const bool onFineRegions = regionWarpRuns && !edges;
            DenseRefineOptions refineOptions = denseOptions;
            if (onFineRegions && !options.refineAfterRegionWarp)
                for (DenseLevel& level : refineOptions.levels)
                    level.iterations = 0; // measure only
            const DenseRefinement dense = refineDense(
                g.grey, g.weight, g.mx, g.my, onFineRegions ? options.regionLabels : atlasLabels,
                plane, refineOptions);
            r.quality.explainedBeforeRefine = dense.explainedBefore;
            r.quality.explainedAfterRefine = dense.explainedAfter;
            r.quality.refined = dense.accepted;
            if (dense.accepted)
                r.warp = addToWarp(r.warp, g.ws, dense.ux, dense.uy);
            if (result) {
                cv::resize(dense.confidence, r.confidence, g.ws, 0, 0, cv::INTER_LINEAR);
                r.regionConfidence =
                    meanByLabel(dense.confidence, r.warpedLabels(atlasLabels, g.gs), g.weight);
            }
            lap("refine");
        }
        // Tissue cannot lie over itself: where the final map folds (Jacobian determinant of the
        // opposite sign to the affine's), the field around the fold is relaxed to the harmonic
        // interpolation of its surroundings, which moves nothing else.
        for (int round = 0; round < options.foldRepairs; ++round) {
            const cv::Mat j = mapJacobian(r.atlasFromWorking, r.warp);
            if (j.empty())
                break;
            cv::Mat folded = det(r.atlasFromWorking) > 0 ? j <= 0 : j >= 0;
            if (cv::countNonZero(folded) == 0)
                break;
            const int k = 2 * (2 + round) + 1;
            cv::dilate(folded, folded, cv::getStructuringElement(cv::MORPH_RECT, cv::Size(k, k)));
            r.warp = relaxWithin(r.warp, folded);
            ++r.quality.foldRepairs;
            r.quality.foldRepairNodes += cv::countNonZero(folded);
        }
        lap("fold-repair");
    };
    // The result's map: with the region warp, without the edge warps unless asked
    // (RegistrationOptions::edgeWarpWithRegions).
    const bool resultEdges = edgeWarps && (options.edgeWarpWithRegions || !regionWarpRuns);
    const bool resultSmooth = resultEdges && options.smoothWarp;
    // The damage check judges the section against the map its rules were made on: the edge
    // warps without the smooth one (RegistrationOptions::damageWithoutSmooth). When the result's
    // map differs from it, the two run from the affine side by side, each on its own copy (one
    // step, "warp-both", in the timings).
    std::optional<DisplacementField> damageWarp;
    if (options.detectDamage && edgeWarps &&
        ((resultSmooth && options.damageWithoutSmooth) || !resultEdges)) {
        Registration stiff = reg;
        runTasks(2, [&](int task) {
            if (task == 0)
                nonLinearStages(stiff, true, false, false, false);
            else
                nonLinearStages(reg, resultEdges, resultSmooth, false, true);
        });
        damageWarp = std::move(stiff.warp);
        timer.lap("warp-both");
    } else {
        nonLinearStages(reg, resultEdges, resultSmooth, true, true);
    }
    reg.quality.minJacobian = minJacobianRelative(reg.atlasFromWorking, reg.warp);

    std::vector<cv::Point2f> mp, mn;
    mapThrough(reg.sectionEdges, reg.atlasFromWorking, reg.warp, mp, mn);
    const std::vector<Match> matches =
        findMatches(mp, mn, reg.atlasEdges, atlasGrid, finalDist, 5, true, TargetRule::PointToLine);

    reg.quality.correspondences = static_cast<int>(matches.size());
    double ss = 0;
    for (const Match& m : matches)
        ss += std::pow(cv::norm(cv::Point2d(mp[m.source]) - m.target), 2);
    reg.quality.residualFinal = matches.empty() ? 0 : std::sqrt(ss / double(matches.size()));
    const PointGrid mappedGrid(mp, float(finalDist));
    reg.quality.atlasBoundaryMatched = shareMatched(reg.atlasEdges.points, mappedGrid, atlasH / 80);
    reg.quality.sectionEdgesMatched = shareMatched(mp, atlasGrid, atlasH / 80);
    reg.quality.scaleAtlasPxPerImagePx = std::sqrt(std::abs(det(reg.affineAtlasFromImage())));
    timer.lap("quality");

    if (options.detectDamage) {
        // Beyond the paper: tissue the atlas expects but the section lacks, and detached pieces.
        // What the mapped atlas (labels seen in the working frame) expects: its brain, the brain
        // without ventricles, and the parts apart across fissures.
        const auto expectationOf = [&](const cv::Mat& labelsSeen) {
            AtlasExpectation e;
            e.brain = labelsSeen != 0;
            e.tissue = e.brain & ~(partMap(labelsSeen, {options.ventricleIds}) != 0);
            if (options.separateParts.size() > 1)
                e.parts = partMap(labelsSeen, options.separateParts);
            return e;
        };
        // Judged against the map without the smooth warp when one was kept aside; the result
        // keeps the final map.
        if (damageWarp)
            std::swap(reg.warp, *damageWarp);
        const cv::Mat seen = reg.warpedLabels(atlasLabels, reg.workingGrey.size());
        const AtlasExpectation expected = expectationOf(seen);
        const cv::Mat& expectedBrain = expected.brain;
        const cv::Mat ventricles = expectedBrain & ~expected.tissue;
        // Small pieces set aside as debris where the atlas expects brain are tissue there (a
        // lobe cut apart), not glass.
        const cv::Mat sectionTissue =
            prepared->tissueMaskFine | piecesInside(prepared->smallPiecesFine, expectedBrain, 0.7);
        // The same against the ICP affine alone (DamageParams::followedBites): the outline pull
        // and the warps bend the atlas onto a cut edge, the affine cannot.
        const auto underAffine = [&reg](auto&& f) {
            DisplacementField warp = std::exchange(reg.warp, DisplacementField());
            f();
            reg.warp = std::move(warp);
        };
        // Only where Algorithm 2 found a deep asymmetric concavity (followedGaps asks for one).
        const bool lookForBites = options.damage.followedBites && !damagedOutline.empty() &&
                                  cv::countNonZero(damagedOutline) > 0;
        AtlasExpectation expectedAffine;
        if (lookForBites)
            underAffine([&] {
                expectedAffine =
                    expectationOf(reg.warpedLabels(atlasLabels, reg.workingGrey.size()));
            });
        // Gaps, fold bands and knife chatter, and the gaps against the affine, do not depend on
        // each other: side by side.
        std::vector<DamageRegion> regions, folds, affineGaps, chatter;
        runTasks(lookForBites ? 3 : 2, [&](int task) {
            if (task == 0)
                regions = tissueDamage(sectionTissue, expected, brainWidth, options.damage,
                                       fragments, reg.workingGrey, damagedOutline);
            else if (task == 1) {
                folds = foldBands(prepared->level, sectionTissue, expected.tissue, seen, brainWidth,
                                  options.damage);
                chatter = chatterBands(prepared->level, sectionTissue, brainWidth, options.damage);
            } else
                affineGaps = tissueDamage(sectionTissue, expectedAffine, brainWidth, options.damage,
                                          fragments, reg.workingGrey, damagedOutline);
        });
        // The atlas midline (the brain's centroid column), into the image by the affine: the
        // longitudinal fissure and the third ventricle lie along it.
        Midline midline;
        if (const cv::Moments am = cv::moments(atlasMask, true); am.m00 > 0) {
            const double mx = am.m10 / am.m00;
            const cv::Matx23d imageFromAtlas = invert(reg.affineAtlasFromImage());
            const cv::Point2d a = apply(imageFromAtlas, cv::Point2d(mx, 0));
            const cv::Point2d b = apply(imageFromAtlas, cv::Point2d(mx, atlasLabels.rows));
            midline = {cv::Point2f(a), cv::Point2f(b)};
        }
        const auto ws = static_cast<float>(reg.workingScale);
        std::vector<DamageRegion> followed = followedGaps(
            std::move(affineGaps), regions, damagedOutline, Midline{midline.a * ws, midline.b * ws},
            options.damage.fissureRingFrac * brainWidth, options.damage);
        for (DamageRegion& d : folds)
            regions.push_back(std::move(d));
        // Report in full-resolution pixels.
        const double s = reg.workingScale;
        toFullPixels(regions, s);
        toFullPixels(followed, s);
        toFullPixels(chatter, s);
        // Gaps no wider than a crack along it are that fissure, as for the cracks below.
        dropAlongMidline(regions, midline, options.damage.fissureRingFrac * brainWidth / s,
                         options.damage.crackMaxWidthPx / crackScale);
        timer.lap("damage");
        // Thin cracks, at full resolution (up to crackMaxSidePx): glass lines narrower than the
        // working image shows.
        if (crackGrey) {
            const cv::Mat& grey = *crackGrey;
            const auto up = [&](const cv::Mat& m) {
                cv::Mat o;
                cv::resize(m, o, crackSize, 0, 0, cv::INTER_NEAREST);
                return o;
            };
            AtlasExpectation fullExpected{cv::Mat(), up(expectedBrain), cv::Mat()};
            const auto c = static_cast<float>(crackScale);
            const Midline crackMidline{midline.a * c, midline.b * c};
            if (!expected.parts.empty())
                fullExpected.parts = up(expected.parts);
            // The mapped regions the section shows dark (an unstained tract): a dark line in
            // one is the region's own.
            if (options.damage.crackDarkness > 0)
                fullExpected.dark = up(darkAtlasRegions(reg.workingGrey, seen, expectedBrain,
                                                        greyLevels(reg.workingGrey, sectionTissue),
                                                        options.damage.crackDarkness));
            cv::Mat known = cv::Mat::zeros(crackSize, CV_8U);
            for (const DamageRegion& d : regions) {
                const std::vector<cv::Point> poly = pixelPolygon(d.polygon, crackScale);
                if (poly.size() >= 3)
                    cv::fillPoly(known, std::vector<std::vector<cv::Point>>{poly}, cv::Scalar(255));
            }
            std::vector<DamageRegion> pieces;
            const cv::Mat tissueAtCracks = up(sectionTissue);
            std::vector<DamageRegion> cracks = thinCracks(
                grey, tissueAtCracks, fullExpected, up(ventricles), brainWidth / s * crackScale,
                options.damage, crackMidline, known, &pieces);
            toFullPixels(cracks, crackScale);
            toFullPixels(pieces, crackScale);
            for (DamageRegion& d : cracks)
                regions.push_back(std::move(d));
            // Where a crack narrows to a shallow line, the pieces beyond continue its tear.
            for (DamageRegion& d :
                 continueTears(regions, pieces, grey, tissueAtCracks, brainWidth / s * crackScale,
                               options.damage, crackScale))
                regions.push_back(std::move(d));
        }
        // Bilateral anatomy is not damage: a gap whose mirror image across the brain's midline
        // (through the registration, in atlas px) shows glass in the section too has a twin.
        dropMirroredGaps(regions, reg, sectionTissue, atlasMask, brainWidth, options.damage);
        // Misfit is not damage: a gap with tissue beside it where the atlas expects none lies
        // where the atlas fit cannot be trusted (markMisfit, in working px).
        markMisfit(regions, sectionTissue, expected, brainWidth, options.damage, fragments, s);
        // A bite the warp followed is judged as the affine placed the atlas: its twin across the
        // midline and misplaced tissue beside it (an affine that is merely off leaves a crescent
        // of tissue beyond its outline, as any misplaced boundary does).
        if (!followed.empty()) {
            underAffine([&] {
                dropMirroredGaps(followed, reg, sectionTissue, atlasMask, brainWidth,
                                 options.damage);
            });
            markMisfit(followed, sectionTissue, expectedAffine, brainWidth, options.damage,
                       fragments, s);
            for (DamageRegion& d : followed)
                regions.push_back(std::move(d));
        }
        // Knife chatter is no gap: neither the mirror nor the misfit judges it.
        for (DamageRegion& d : chatter)
            regions.push_back(std::move(d));
        // The glass inside the tissue where the atlas expects tissue (the expected tissue eroded
        // by the registration slack, as tissueDamage takes it), whatever the rules made of it,
        // in atlas px through the map the gaps were found against (the series context:
        // glassOutlines); pieces as small as the smallest gap looked at.
        reg.glassAtlas = glassOutlines(
            reg,
            glassWhereTissueIsExpected(
                sectionTissue, expected.tissue,
                std::max(1, static_cast<int>(std::lround(options.damage.slackFrac * brainWidth)))),
            options.damage.minRegionShare / 4 * std::max(1, cv::countNonZero(sectionTissue)));
        if (damageWarp) {
            // Where the gaps lie in the atlas (the series context compares them with the
            // neighbours'), through the map they were found against.
            for (DamageRegion& d : regions)
                d.atlasOutline = atlasDamageOutline(reg, d);
            std::swap(reg.warp, *damageWarp);
        }
        const DamageDecision decision = decideDamage(regions, brainWidth / s, options.damage);
        reg.damageScore = decision.score;
        reg.damageVerdict = decision.verdict;
        reg.damaged = decision.verdict == DamageVerdict::Damaged;
        reg.damageSummary = damageSummary(regions);
        for (const DamageRegion& d : regions)
            reg.damageFraction += d.share;
        reg.damage = std::move(regions);
        timer.lap("damage-cracks");
    }
    timer.total();
    return reg;
}

} // namespace slicestation::pipeline
