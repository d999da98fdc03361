#include "slicestation/pipeline/damage.hpp"

#include "side_by_side.hpp"
#include "slicestation/pipeline/affine.hpp"
#include "slicestation/pipeline/mask_ops.hpp"
#include "slicestation/pipeline/medial_axis.hpp"
#include "slicestation/pipeline/point_grid.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <functional>
#include <limits>
#include <map>
#include <optional>
#include <tuple>
#include <unordered_map>
#include <utility>

namespace slicestation::pipeline {
namespace {

std::vector<cv::Point2f> polygonOf(const cv::Mat& regionMask, cv::Point offset = {}) {
    std::vector<std::vector<cv::Point>> contours;
    cv::findContours(regionMask.clone(), contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_SIMPLE,
                     offset);
    if (contours.empty())
        return {};
    const auto& c = *std::max_element(contours.begin(), contours.end(), [](auto& a, auto& b) {
        return cv::contourArea(a) < cv::contourArea(b);
    });
    std::vector<cv::Point> simple;
    cv::approxPolyDP(c, simple, 1.0, true);
    std::vector<cv::Point2f> out;
    for (const auto& p : simple)
        out.emplace_back(float(p.x), float(p.y));
    return out;
}

/// `box` grown by `margin` on every side, within an image of `size`.
cv::Rect grown(const cv::Rect& box, int margin, cv::Size size) {
    return (box + cv::Size(2 * margin, 2 * margin) - cv::Point(margin, margin)) &
           cv::Rect(0, 0, size.width, size.height);
}

/// Each row of a structuring element (odd size, centre anchor) as a run centred on the anchor:
/// its half width, -1 for an empty row; nullopt when some row is not one centred run (the
/// kernel is not an ellipse).
std::optional<std::vector<int>> centredRunHalfWidths(const cv::Mat& kernel) {
    const int ax = kernel.cols / 2;
    std::vector<int> halfWidth(static_cast<size_t>(kernel.rows), -1);
    for (int ky = 0; ky < kernel.rows; ++ky) {
        const std::uint8_t* k = kernel.ptr<std::uint8_t>(ky);
        int first = -1, last = -1;
        for (int kx = 0; kx < kernel.cols; ++kx)
            if (k[kx]) {
                if (first < 0)
                    first = kx;
                last = kx;
            }
        if (first < 0)
            continue;
        if (ax - first != last - ax || cv::countNonZero(kernel.row(ky)) != last - first + 1)
            return std::nullopt;
        halfWidth[static_cast<size_t>(ky)] = ax - first;
    }
    return halfWidth;
}

/// cv::dilate of a 0/255 mask (CV_8U, not a view into a larger image: nothing beyond its edge
/// counts) by an elliptic structuring element `kernel` (getStructuringElement, odd size, centre
/// anchor), the same pixels set; 255 where set. Each of the ellipse's rows is a run centred on
/// the anchor, so a pixel is set when, for some row dy of the kernel, the nearest set pixel on
/// image row y + dy lies within that run's half width: one distance per pixel along the rows,
/// then one comparison per kernel row, instead of one maximum per kernel pixel (a 71 px disc
/// has 4000).
cv::Mat dilateEllipse(const cv::Mat& mask, const cv::Mat& kernel) {
    CV_Assert(mask.type() == CV_8U && kernel.type() == CV_8U && kernel.rows % 2 == 1 &&
              kernel.cols % 2 == 1);
    const int ay = kernel.rows / 2;
    const std::optional<std::vector<int>> rowRuns = centredRunHalfWidths(kernel);
    if (!rowRuns) { // Not an ellipse: OpenCV's own dilation then.
        cv::Mat out;
        cv::dilate(mask, out, kernel);
        return out > 0;
    }
    const std::vector<int>& halfWidth = *rowRuns;
    // Distance along the row to the nearest set pixel, capped.
    const int cap = std::min(32000, kernel.cols + 1);
    cv::Mat along(mask.size(), CV_16S);
    for (int y = 0; y < mask.rows; ++y) {
        const std::uint8_t* m = mask.ptr<std::uint8_t>(y);
        std::int16_t* d = along.ptr<std::int16_t>(y);
        int run = cap;
        for (int x = 0; x < mask.cols; ++x) {
            run = m[x] ? 0 : std::min(cap, run + 1);
            d[x] = static_cast<std::int16_t>(run);
        }
        run = cap;
        for (int x = mask.cols - 1; x >= 0; --x) {
            run = m[x] ? 0 : std::min(cap, run + 1);
            d[x] = static_cast<std::int16_t>(std::min<int>(d[x], run));
        }
    }
    // Output row y takes image row y + ky - ay through kernel row ky: whole shifted bands at
    // once.
    cv::Mat out = cv::Mat::zeros(mask.size(), CV_8U), within;
    for (int ky = 0; ky < kernel.rows; ++ky) {
        const int a = halfWidth[static_cast<size_t>(ky)];
        const int shift = ky - ay;
        const int y0 = std::max(0, -shift), y1 = std::min(mask.rows, mask.rows - shift);
        if (a < 0 || y1 <= y0)
            continue;
        cv::compare(along.rowRange(y0 + shift, y1 + shift), cv::Scalar(a), within, cv::CMP_LE);
        cv::Mat band = out.rowRange(y0, y1);
        band |= within;
    }
    return out;
}

/// cv::morphologyEx(src, MORPH_CLOSE, kernel) of a CV_32F image by an elliptic `kernel` (odd
/// size, centre anchor), the same values: the maximum (minimum) over the ellipse is the maximum
/// over its rows of the maximum along each row's centred run, so the runs are taken by OpenCV's
/// separable row filters (one per distinct run width) and the rows combined in shifted bands.
/// Pixels beyond the image's edge count for nothing, as in OpenCV's default border; `src` may
/// be a view, but a pixel whose ellipse reaches past the view's edge may then differ.
cv::Mat closeEllipse(const cv::Mat& src, const cv::Mat& kernel) {
    CV_Assert(src.type() == CV_32F && kernel.type() == CV_8U && kernel.rows % 2 == 1 &&
              kernel.cols % 2 == 1);
    const int ay = kernel.rows / 2;
    const std::optional<std::vector<int>> rowRuns = centredRunHalfWidths(kernel);
    if (!rowRuns) {
        cv::Mat out;
        cv::morphologyEx(src, out, cv::MORPH_CLOSE, kernel);
        return out;
    }
    const std::vector<int>& halfWidth = *rowRuns;
    const auto byRows = [&](const cv::Mat& in, int op) {
        std::map<int, cv::Mat> runs;
        for (const int a : halfWidth)
            if (a >= 0 && !runs.count(a)) {
                if (a == 0)
                    runs[a] = in;
                else
                    cv::morphologyEx(in, runs[a], op,
                                     cv::getStructuringElement(cv::MORPH_RECT, {2 * a + 1, 1}));
            }
        cv::Mat out = runs.at(halfWidth[static_cast<size_t>(ay)]).clone();
        for (int ky = 0; ky < kernel.rows; ++ky) {
            const int a = halfWidth[static_cast<size_t>(ky)];
            const int shift = ky - ay;
            const int y0 = std::max(0, -shift), y1 = std::min(in.rows, in.rows - shift);
            if (a < 0 || shift == 0 || y1 <= y0)
                continue;
            cv::Mat band = out.rowRange(y0, y1);
            const cv::Mat from = runs.at(a).rowRange(y0 + shift, y1 + shift);
            if (op == cv::MORPH_DILATE)
                cv::max(band, from, band);
            else
                cv::min(band, from, band);
        }
        return out;
    };
    return byRows(byRows(src, cv::MORPH_DILATE), cv::MORPH_ERODE);
}

/// The glass of `grey` over `where`: its median level and noise (1.4826 x the median absolute
/// deviation from that level, at least 1e-6).
struct GlassStats {
    float level = 0;
    float noise = 0;
};
GlassStats glassStats(const cv::Mat& grey, const cv::Mat& where) {
    // As percentile(grey, 0.5, where) and then percentile(|grey - level|, 0.5, where), on the
    // same strided sample, without the deviation image: the sampled pixels' deviations are all
    // the second percentile reads.
    const int step = std::max(1, static_cast<int>(std::sqrt(grey.total() / 250000.0)));
    std::vector<float> v;
    for (int y = 0; y < grey.rows; y += step) {
        const float* row = grey.ptr<float>(y);
        const std::uint8_t* ok = where.ptr<std::uint8_t>(y);
        for (int x = 0; x < grey.cols; x += step)
            if (ok[x])
                v.push_back(row[x]);
    }
    GlassStats g;
    if (v.empty()) {
        g.noise = 1e-6f;
        return g;
    }
    const auto k = static_cast<size_t>(0.5 * static_cast<double>(v.size() - 1));
    g.level = kthSmallest(v, k);
    for (float& x : v)
        x = std::abs(x - g.level);
    g.noise = std::max(1e-6f, 1.4826f * kthSmallest(v, k));
    return g;
}

/// `op` (a neighbourhood operation reaching at most `reachPx` from each pixel, giving a CV_8U
/// mask) evaluated only on the 64 px tiles of an image of `size` that hold a pixel of `need`
/// (CV_8U), each run of such tiles along a row grown by `reachPx`, so that on those tiles the
/// result is the whole image's; 0 elsewhere. For the closings and dilations that only matter
/// at the few candidate pixels of a crack.
template <class Op> cv::Mat onNeededTiles(const cv::Mat& need, int reachPx, const Op& op) {
    constexpr int kTile = 64;
    cv::Mat out = cv::Mat::zeros(need.size(), CV_8U);
    const cv::Rect image(0, 0, need.cols, need.rows);
    std::vector<cv::Rect> runs;
    for (int y = 0; y < need.rows; y += kTile) {
        const int h = std::min(kTile, need.rows - y);
        int runStart = -1;
        // One step past the last tile, to end a run there.
        for (int x = 0; x < need.cols + kTile; x += kTile) {
            const bool needed =
                x < need.cols &&
                cv::countNonZero(need(cv::Rect(x, y, std::min(kTile, need.cols - x), h))) > 0;
            if (needed && runStart < 0)
                runStart = x;
            if (!needed && runStart >= 0) {
                runs.emplace_back(runStart, y, std::min(x, need.cols) - runStart, h);
                runStart = -1;
            }
        }
    }
    // Each run writes only its own pixels: side by side on OpenCV's threads.
    runTasks(int(runs.size()), [&](int i) {
        const cv::Rect& run = runs[size_t(i)];
        const cv::Rect reach = grown(run, reachPx, need.size()) & image;
        const cv::Mat r = op(reach);
        r(run - reach.tl()).copyTo(out(run));
    });
    return out;
}

} // namespace

std::string_view toString(DamageKind kind) noexcept {
    switch (kind) {
    case DamageKind::Tear:
        return "tear";
    case DamageKind::Missing:
        return "missing";
    case DamageKind::Fold:
        return "fold";
    case DamageKind::Fragment:
        return "fragment";
    case DamageKind::Chatter:
        return "chatter";
    }
    return "unknown";
}

std::vector<cv::Point2f> subdivide(const std::vector<cv::Point2f>& polygon, double maxSegmentPx) {
    std::vector<cv::Point2f> out;
    for (size_t i = 0; i < polygon.size(); ++i) {
        const cv::Point2f a = polygon[i], b = polygon[(i + 1) % polygon.size()];
        const int pieces = std::max(1, static_cast<int>(std::ceil(cv::norm(b - a) / maxSegmentPx)));
        for (int k = 0; k < pieces; ++k)
            out.push_back(a + (b - a) * (float(k) / float(pieces)));
    }
    return out;
}

Outline tissueOutline(const cv::Mat& tissueMask, double maxSegmentPx) {
    Outline out;
    std::vector<std::vector<cv::Point>> contours;
    cv::findContours(tissueMask.clone(), contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_NONE);
    if (contours.empty())
        return out;
    const auto& c = *std::max_element(contours.begin(), contours.end(), [](auto& a, auto& b) {
        return cv::contourArea(a) < cv::contourArea(b);
    });
    std::vector<cv::Point> simple;
    cv::approxPolyDP(c, simple, 1.0, true);
    for (const auto& p : simple) {
        const cv::Point2f q(float(p.x), float(p.y));
        if (out.points.empty() || q != out.points.back())
            out.points.push_back(q);
    }
    while (out.points.size() > 1 && out.points.front() == out.points.back())
        out.points.pop_back();
    out.points = subdivide(out.points, maxSegmentPx);
    const size_t n = out.points.size();
    for (size_t i = 0; i < n; ++i) {
        const cv::Point2f d = out.points[(i + 1) % n] - out.points[(i + n - 1) % n];
        const float len = std::hypot(d.x, d.y);
        out.normals.push_back(len > 0 ? cv::Point2f(-d.y / len, d.x / len) : cv::Point2f(0, 1));
    }
    return out;
}

std::vector<Concavity> deepConcavities(const Outline& outline, double alphaPx) {
    std::vector<Concavity> out;
    const ExteriorTriangulation ext = exteriorMedialAxis(outline.points);
    for (const MedialBranch& b : ext.branches) {
        if (b.length < alphaPx)
            break; // sorted longest first
        Concavity c;
        c.axisLength = b.length;
        for (int v : b.outlineVertices) {
            c.points.push_back(outline.points[v]);
            c.normals.push_back(outline.normals[v]);
        }
        out.push_back(std::move(c));
    }
    return out;
}

void markSymmetric(std::vector<Concavity>& concavities, const Outline& outline,
                   const cv::Matx23d& mirror, double brainWidthPx, const DamageParams& params) {
    const float radius = float(params.symmetryRadiusFrac * brainWidthPx);
    const PointGrid grid(outline.points, std::max(radius, 1.0f));
    const double cosMax = std::cos(params.symmetryAngleDeg * CV_PI / 180.0);
    for (Concavity& c : concavities) {
        size_t partnered = 0;
        for (size_t i = 0; i < c.points.size(); ++i) {
            // The paper looks in a 3x3 neighbourhood at its resolution; here the radius scales
            // with the brain, and the normal must mirror too.
            const cv::Point2f q(apply(mirror, c.points[i]));
            const cv::Point2d m = mapNormal(mirror, c.normals[i]);
            bool found = false;
            grid.forEachWithin(q, radius, [&](int j, float) {
                if (std::abs(m.x * outline.normals[j].x + m.y * outline.normals[j].y) >= cosMax)
                    found = true;
            });
            if (found)
                ++partnered;
        }
        c.symmetric = !c.points.empty() &&
                      double(partnered) >= params.symmetricShare * double(c.points.size());
    }
}

cv::Mat concavityExclusion(const std::vector<Concavity>& concavities, cv::Size size,
                           double marginPx) {
    cv::Mat mask = cv::Mat::zeros(size, CV_8U);
    for (const Concavity& c : concavities) {
        if (c.symmetric || c.points.size() < 3)
            continue;
        std::vector<cv::Point2f> hull;
        cv::convexHull(c.points, hull);
        std::vector<cv::Point> poly;
        for (const auto& p : hull)
            poly.emplace_back(cvRound(p.x), cvRound(p.y));
        cv::fillConvexPoly(mask, poly, cv::Scalar(255));
    }
    if (cv::countNonZero(mask) == 0)
        return mask; // nothing to grow (most sections)
    const int m = std::max(1, static_cast<int>(std::lround(marginPx)));
    return dilateEllipse(
        mask, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * m + 1, 2 * m + 1)));
}

bool isGap(const DamageRegion& d) {
    return d.kind == DamageKind::Tear || d.kind == DamageKind::Missing;
}

namespace {

/// Whether a polygon reaches within `ringPx` of the midline's line or crosses it (its vertices'
/// signed distances to the line span [-ringPx, ringPx] or more). False when the midline is
/// unknown (a == b).
bool reachesMidline(const std::vector<cv::Point2f>& polygon, const Midline& midline,
                    double ringPx) {
    const cv::Point2f along = midline.b - midline.a;
    const double length = std::hypot(along.x, along.y);
    if (length <= 0 || polygon.empty())
        return false;
    double lo = std::numeric_limits<double>::max(), hi = -lo;
    for (const cv::Point2f& p : polygon) {
        const double side = along.cross(p - midline.a) / length;
        lo = std::min(lo, side);
        hi = std::max(hi, side);
    }
    return lo <= ringPx && hi >= -ringPx;
}

/// Whether a region (CV_8U, its top-left at `offset`) runs along the expected midline: at least
/// 70% of its pixels within `ringPx` of it and its principal axis within 20 degrees of it.
bool alongMidline(const cv::Mat& region, cv::Point offset, const Midline& midline, int ringPx) {
    const cv::Point2f dir = midline.b - midline.a;
    const double len = std::hypot(dir.x, dir.y);
    if (len <= 0)
        return false;
    const cv::Point2d u(dir.x / len, dir.y / len);
    std::vector<cv::Point> pts;
    cv::findNonZero(region, pts);
    if (pts.empty())
        return false;
    int near = 0;
    for (const cv::Point& p : pts) {
        const cv::Point2d d(p.x + offset.x - midline.a.x, p.y + offset.y - midline.a.y);
        if (std::abs(d.x * u.y - d.y * u.x) <= ringPx)
            ++near;
    }
    if (near < 0.7 * double(pts.size()))
        return false;
    const cv::Moments m = cv::moments(region, true);
    const double angle = 0.5 * std::atan2(2 * m.mu11, m.mu20 - m.mu02);
    const double cosTurn = std::abs(std::cos(angle) * u.x + std::sin(angle) * u.y);
    return cosTurn >= std::cos(20.0 * 3.14159265358979 / 180.0);
}
/// The 8-connected pieces of a mask, labelled only where asked: a crack candidate needs the
/// areas of the few dim pieces beside it, and labelling the whole full-resolution mask for them
/// cost more than all the candidates' other tests (the areas are those
/// cv::connectedComponentsWithStats gives).
class PiecesOnDemand {
public:
    /// `makeMask` gives the mask (CV_8U) when it is first needed.
    explicit PiecesOnDemand(std::function<cv::Mat()> makeMask) : makeMask_(std::move(makeMask)) {}
    /// The label (1, 2, ...) of the piece holding (x, y), 0 where the mask is not set.
    int pieceAt(int x, int y) {
        if (mask_.empty()) {
            mask_ = makeMask_();
            labels_ = cv::Mat::zeros(mask_.size(), CV_32S);
        }
        if (!mask_.at<std::uint8_t>(y, x))
            return 0;
        const std::int32_t label = labels_.at<std::int32_t>(y, x);
        return label != 0 ? label : fill(x, y);
    }
    /// The area in pixels of piece `label` (a value pieceAt returned).
    int area(int label) const { return area_[static_cast<std::size_t>(label - 1)]; }
    /// The label of (x, y) if its piece was labelled already (by pieceAt), else 0; labels nothing.
    int labelledAt(int x, int y) const {
        return labels_.empty() ? 0 : labels_.at<std::int32_t>(y, x);
    }

private:
    int fill(int x0, int y0) {
        const auto id = static_cast<std::int32_t>(area_.size() + 1);
        int count = 0;
        stack_.assign(1, cv::Point(x0, y0));
        labels_.at<std::int32_t>(y0, x0) = id;
        while (!stack_.empty()) {
            const cv::Point p = stack_.back();
            stack_.pop_back();
            ++count;
            for (int dy = -1; dy <= 1; ++dy) {
                const int y = p.y + dy;
                if (y < 0 || y >= mask_.rows)
                    continue;
                const std::uint8_t* m = mask_.ptr<std::uint8_t>(y);
                std::int32_t* l = labels_.ptr<std::int32_t>(y);
                for (int x = std::max(0, p.x - 1); x <= std::min(mask_.cols - 1, p.x + 1); ++x)
                    if (m[x] && l[x] == 0) {
                        l[x] = id;
                        stack_.emplace_back(x, y);
                    }
            }
        }
        area_.push_back(count);
        return id;
    }

    std::function<cv::Mat()> makeMask_;
    cv::Mat mask_, labels_;
    std::vector<int> area_;
    std::vector<cv::Point> stack_;
};

/// The dim (dark, not glass) pieces that `region` (at `offset` in the dim mask) touches, and
/// their area: a crack's are its own blurred flanks; the thin end of a dim structure (a dark
/// fibre tract narrowing) leads into the structure's wide body.
struct DimBody {
    std::vector<int> pieces; ///< their labels in `dim`
    double area = 0;
};

DimBody dimBodyOf(const cv::Mat& region, cv::Point offset, PiecesOnDemand& dim) {
    cv::Mat near;
    cv::dilate(region, near, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(5, 5)));
    DimBody body;
    for (int y = 0; y < near.rows; ++y) {
        const std::uint8_t* m = near.ptr<std::uint8_t>(y);
        for (int x = 0; x < near.cols; ++x) {
            if (!m[x])
                continue;
            const int id = dim.pieceAt(x + offset.x, y + offset.y);
            if (id != 0 &&
                std::find(body.pieces.begin(), body.pieces.end(), id) == body.pieces.end()) {
                body.pieces.push_back(id);
                body.area += dim.area(id);
            }
        }
    }
    return body;
}

/// The median of `light` (the grey image of the line's box, at `offset` in the dim mask) over
/// the body's pixels in `beside` (the band around the line, CV_8U, the same size); 0 when none
/// lies there. The thin end of a dim structure is at the structure's level; a crack crossing a
/// dim region is a valley below it.
float dimBodyLevel(const DimBody& body, cv::Point offset, const PiecesOnDemand& dim,
                   const cv::Mat& light, const cv::Mat& beside) {
    cv::Mat inBody = cv::Mat::zeros(beside.size(), CV_8U);
    for (int y = 0; y < beside.rows; ++y) {
        const std::uint8_t* b = beside.ptr<std::uint8_t>(y);
        for (int x = 0; x < beside.cols; ++x) {
            // The body's pieces are labelled whole already.
            const int id = b[x] ? dim.labelledAt(x + offset.x, y + offset.y) : 0;
            if (id != 0 &&
                std::find(body.pieces.begin(), body.pieces.end(), id) != body.pieces.end())
                inBody.at<std::uint8_t>(y, x) = 255;
        }
    }
    return cv::countNonZero(inBody) > 0 ? percentile(light, 0.5, inBody) : 0.0f;
}

/// darkValleys on a grey image already blurred by 0.7 px.
cv::Mat valleysOf(const cv::Mat& sharp, GreyLevels levels, const DamageParams& params, int discPx) {
    if (levels.tissue <= levels.glass)
        return cv::Mat::zeros(sharp.size(), CV_8U);
    // A line under a pixel wide is only darker than the tissue beside it: dark against the
    // tissue's level, and a valley, darker than the tissue on both sides (the black top-hat of a
    // 5 px disc), which neither dim tissue nor its edge against bright tissue is.
    const cv::Mat closed =
        closeEllipse(sharp, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(discPx, discPx)));
    const float span = levels.tissue - levels.glass;
    const float darkBelow = levels.glass + static_cast<float>(params.threadDarkness) * span;
    const float deeperThan = static_cast<float>(params.threadDepth) * span;
    return (sharp < darkBelow) & ((closed - sharp) > deeperThan);
}

} // namespace

std::vector<DamageRegion> thinCracks(const cv::Mat& grey, const cv::Mat& tissue,
                                     const AtlasExpectation& expected, const cv::Mat& ventricles,
                                     double brainWidthPx, const DamageParams& params,
                                     const Midline& midline, const cv::Mat& known,
                                     std::vector<DamageRegion>* pieces) {
    CV_Assert(grey.type() == CV_32F && tissue.type() == CV_8U && tissue.size() == grey.size() &&
              expected.brain.size() == grey.size() && ventricles.size() == grey.size() &&
              (known.empty() || known.size() == grey.size()) &&
              (expected.parts.empty() || expected.parts.size() == grey.size()) &&
              (expected.dark.empty() || expected.dark.size() == grey.size()));
    std::vector<DamageRegion> out;
    const double tissueArea = cv::countNonZero(tissue);
    if (tissueArea <= 0 || brainWidthPx <= 0)
        return out;
    // Work in the box of the section and the mapped brain with a band of glass around it.
    const cv::Rect work = grown(cv::boundingRect(tissue | expected.brain), 24, grey.size());
    if (work.area() < grey.size().area()) {
        const auto crop = [&](const cv::Mat& m) { return m.empty() ? m : m(work); };
        const AtlasExpectation inBox{crop(expected.tissue), crop(expected.brain),
                                     crop(expected.parts), crop(expected.dark)};
        const cv::Point2f shift(float(work.x), float(work.y));
        const Midline boxMidline{midline.a - shift, midline.b - shift};
        const std::size_t firstPiece = pieces ? pieces->size() : 0;
        out = thinCracks(grey(work), tissue(work), inBox, ventricles(work), brainWidthPx, params,
                         boxMidline, crop(known), pieces);
        for (DamageRegion& d : out)
            for (cv::Point2f& p : d.polygon)
                p += shift;
        for (std::size_t k = firstPiece; pieces && k < pieces->size(); ++k)
            for (cv::Point2f& p : (*pieces)[k].polygon)
                p += shift;
        return out;
    }
    // The glass outside the section, a few pixels away from its blurred edge.
    cv::Mat exterior;
    cv::dilate(fillHoles(tissue), exterior,
               cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(7, 7)));
    exterior = ~exterior;
    if (cv::countNonZero(exterior) < 256)
        return out;
    cv::Mat light;
    cv::GaussianBlur(grey, light, cv::Size(), 0.7);
    const GlassStats glass = glassStats(light, exterior);
    const cv::Mat glassPx =
        light < glass.level + static_cast<float>(params.glassNoiseUnits) * glass.noise;
    const int half = std::max(1, static_cast<int>(std::lround(params.crackMaxWidthPx / 2)));
    // A crack narrower than the optics' blur never reaches the glass level: its middle is a dark
    // valley (darkValleys), as deep as the glass share of the blurred line.
    cv::Mat crackPx = glassPx;
    GreyLevels levels{glass.level, glass.level};
    if (params.crackDarkness > 0) {
        DamageParams valley = params;
        valley.threadDarkness = params.crackDarkness;
        levels.tissue = percentile(light, 0.5, tissue);
        // A valley needs a dark pixel: only the dark tissue that is not glass already needs the
        // closing (within its reach, twice the disc's radius).
        const int disc = 2 * half + 3;
        const float darkBelow = levels.glass + static_cast<float>(valley.threadDarkness) *
                                                   (levels.tissue - levels.glass);
        const cv::Mat need = (light < darkBelow) & tissue & ~glassPx;
        crackPx = glassPx | (onNeededTiles(need, 2 * (disc / 2),
                                           [&](const cv::Rect& r) {
                                               return valleysOf(light(r), levels, valley, disc);
                                           }) &
                             tissue);
    }
    // The dark pixels that are not glass, 8-connected: labelled piece by piece around the
    // candidates that reach the test needing them.
    PiecesOnDemand dim([&] {
        return cv::Mat((light < levels.glass + static_cast<float>(params.crackDarkness) *
                                                   (levels.tissue - levels.glass)) &
                       ~glassPx);
    });
    // Where a crack may be: inside the mapped brain, away from the mapped ventricles. The
    // dilations and the closing below matter only at such pixels, so they are evaluated on the
    // tiles that hold one.
    const int slack = std::max(1, static_cast<int>(std::lround(params.slackFrac * brainWidthPx)));
    const cv::Mat slackDisc =
        cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * slack + 1, 2 * slack + 1));
    const auto dilatedOn = [&](const cv::Mat& mask, const cv::Mat& need) {
        return onNeededTiles(need, slack, [&](const cv::Rect& r) {
            cv::Mat o;
            cv::dilate(mask(r), o, slackDisc);
            return o;
        });
    };
    cv::Mat thin = crackPx & expected.brain;
    thin &= ~dilatedOn(ventricles, thin);
    const cv::Mat crackDisc =
        cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * half + 1, 2 * half + 1));
    thin &= onNeededTiles(thin, 2 * half, [&](const cv::Rect& r) {
        cv::Mat o;
        cv::morphologyEx(~crackPx(r), o, cv::MORPH_CLOSE, crackDisc);
        return o;
    });
    // The dark regions, grown by the registration slack as the ventricles are.
    cv::Mat darkNear;
    if (!expected.dark.empty())
        darkNear = dilatedOn(expected.dark, thin);
    const int ringPx =
        std::max(1, static_cast<int>(std::lround(params.fissureRingFrac * brainWidthPx)));
    // The midline's fissure (and the cleft between the bulbs) is no crack; a crack that starts
    // from it is judged on the part beyond it.
    if (midline.a != midline.b) {
        const cv::Point2f u = midline.b - midline.a;
        const cv::Point2f far = u * (10.0f * float(std::max(grey.rows, grey.cols)) /
                                     std::max(1e-3f, std::hypot(u.x, u.y)));
        cv::line(thin, cv::Point(midline.a - far), cv::Point(midline.a + far), cv::Scalar(0),
                 2 * ringPx + 1);
    }
    cv::Mat tissueParts;
    if (!expected.parts.empty()) {
        tissueParts = cv::Mat::zeros(tissue.size(), CV_8U);
        expected.parts.copyTo(tissueParts, tissue);
    }
    cv::Mat labels, stats;
    const int n = labelComponents(thin, labels, stats);
    const double minLength = params.crackMinFrac * brainWidthPx;
    // Shorter lines are looked at only when the caller collects the pieces of a crack.
    const double pieceLength = pieces && params.crackPieceFrac > 0
                                   ? std::min(minLength, params.crackPieceFrac * brainWidthPx)
                                   : minLength;
    // The tests up to the dim pieces' read only shared images: every line is tested side by
    // side on OpenCV's threads; the rest, whose pieces are labelled on demand, goes in order.
    struct Candidate {
        cv::Rect roi;
        cv::Mat region, beside; ///< the line, and the tissue of the band around it (roi frame)
        double area, length, thickness;
    };
    std::vector<std::optional<Candidate>> candidates(size_t(std::max(n, 1)));
    const auto test = [&](int i) -> std::optional<Candidate> {
        const int w = stats.at<int>(i, cv::CC_STAT_WIDTH), h = stats.at<int>(i, cv::CC_STAT_HEIGHT);
        if (std::max(w, h) < 0.7 * pieceLength)
            return std::nullopt;
        const double area = stats.at<int>(i, cv::CC_STAT_AREA);
        const cv::Rect bounds(stats.at<int>(i, cv::CC_STAT_LEFT), stats.at<int>(i, cv::CC_STAT_TOP),
                              w, h);
        const cv::Rect roi = grown(bounds, ringPx + 1, labels.size());
        const cv::Mat region = labels(roi) == i;
        if (!known.empty() && cv::countNonZero(region & known(roi)) > 0.5 * area)
            return std::nullopt;
        std::vector<cv::Point> pts;
        cv::findNonZero(region, pts);
        const cv::RotatedRect box = cv::minAreaRect(pts);
        const double length = std::max(box.size.width, box.size.height);
        cv::Mat dist;
        cv::distanceTransform(region, dist, cv::DIST_L2, 3);
        double radius = 0;
        cv::minMaxLoc(dist, nullptr, &radius);
        const double thickness = 2 * radius;
        if (length < pieceLength || length < params.crackElongation * std::max(thickness, 1.0))
            return std::nullopt;
        if (!tissueParts.empty() &&
            betweenParts(region, tissueParts(roi), ringPx, params.fissurePurity))
            return std::nullopt;
        // Tissue on both sides: beside a crack (past its blurred edge) lies tissue, not more
        // glass-level speckle, as between the grains of dim textured tissue.
        cv::Mat nearBand, farBand;
        cv::dilate(region, nearBand, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(5, 5)));
        farBand =
            dilateEllipse(region, cv::getStructuringElement(cv::MORPH_ELLIPSE,
                                                            cv::Size(4 * half + 5, 4 * half + 5)));
        const cv::Mat beside = farBand & ~nearBand & tissue(roi);
        const double besideGlass = cv::countNonZero(beside & glassPx(roi)) /
                                   std::max(1.0, double(cv::countNonZero(beside)));
        if (besideGlass > params.crackWallGlass)
            return std::nullopt;
        return Candidate{roi, region, beside, area, length, thickness};
    };
    runTasks(n - 1, [&](int k) { candidates[size_t(k + 1)] = test(k + 1); });
    for (int i = 1; i < n; ++i) {
        if (!candidates[size_t(i)])
            continue;
        const auto& [roi, region, beside, area, length, thickness] = *candidates[size_t(i)];
        if (params.crackDarkness > 0) {
            const DimBody body = dimBodyOf(region, roi.tl(), dim);
            // A large dim body is the line's, unless the line is a valley in it: its core (the
            // darker quarter of its pixels; the rest are its blurred flanks) far below the body.
            if (body.area > params.crackDimBody * area) {
                const float level = dimBodyLevel(body, roi.tl(), dim, light(roi), beside);
                const float lineCore = percentile(light(roi), 0.25, region);
                const bool valley = params.crackBelowBody > 0 && level > levels.glass &&
                                    lineCore <= level - static_cast<float>(params.crackBelowBody) *
                                                            (level - levels.glass);
                if (!valley)
                    continue;
            }
        }
        // Inside a mapped region the section shows dark (an unstained tract), a dark line is
        // that region's own narrow stretch.
        if (!darkNear.empty() && cv::countNonZero(region & darkNear(roi)) > 0.5 * area)
            continue;
        if (alongMidline(region, roi.tl(), midline, ringPx))
            continue;
        DamageRegion d;
        d.kind = DamageKind::Tear;
        d.polygon = polygonOf(region, roi.tl());
        d.areaPx = area;
        d.share = area / tissueArea;
        d.lengthPx = length;
        d.thicknessPx = thickness;
        d.crack = true;
        if (length < minLength)
            pieces->push_back(std::move(d));
        else
            out.push_back(std::move(d));
    }
    return out;
}

namespace {
/// The closest points of two outlines, each a closed polygon of at least one point (the
/// distance between two polygons is reached at a vertex of one of them).
std::pair<cv::Point2f, cv::Point2f> closestPoints(const std::vector<cv::Point2f>& a,
                                                  const std::vector<cv::Point2f>& b) {
    std::pair<cv::Point2f, cv::Point2f> best{a.front(), b.front()};
    double bestD = std::numeric_limits<double>::infinity();
    const auto scan = [&](const std::vector<cv::Point2f>& from, const std::vector<cv::Point2f>& to,
                          bool swapped) {
        for (const cv::Point2f& p : from)
            for (std::size_t k = 0; k < to.size(); ++k) {
                const cv::Point2f q0 = to[k], q1 = to[(k + 1) % to.size()];
                const cv::Point2f d = q1 - q0;
                const float len2 = d.dot(d);
                const float t = len2 > 0 ? std::clamp((p - q0).dot(d) / len2, 0.0f, 1.0f) : 0.0f;
                const cv::Point2f q = q0 + t * d;
                const double dist = cv::norm(p - q);
                if (dist < bestD) {
                    bestD = dist;
                    best = swapped ? std::make_pair(q, p) : std::make_pair(p, q);
                }
            }
    };
    scan(a, b, false);
    scan(b, a, true);
    return best;
}

/// Whether the break between two outlines (mask px of `grey`, CV_32F), from `p` on one to `q`
/// on the other (their closest points), is a fainter stretch of a crack: bridged by pixels of
/// `inside` (CV_8U) darker than the tissue around the break by `depth`, within a box around it
/// as wide as it is long each way.
bool fainterStretch(const cv::Mat& grey, const cv::Mat& inside, const std::vector<cv::Point2f>& a,
                    const std::vector<cv::Point2f>& b, cv::Point2f p, cv::Point2f q, float depth) {
    const double length = cv::norm(p - q);
    const cv::Point2f mid = 0.5f * (p + q);
    const int reach = static_cast<int>(std::ceil(length)) + 2;
    const cv::Rect box =
        cv::Rect(cvRound(mid.x) - reach, cvRound(mid.y) - reach, 2 * reach + 1, 2 * reach + 1) &
        cv::Rect(0, 0, grey.cols, grey.rows);
    if (box.area() == 0)
        return false;
    const auto paint = [&](const std::vector<cv::Point2f>& poly) {
        cv::Mat m = cv::Mat::zeros(box.size(), CV_8U);
        std::vector<cv::Point> pts;
        for (const cv::Point2f& v : poly)
            pts.emplace_back(cvRound(v.x) - box.x, cvRound(v.y) - box.y);
        // A thin line's outline may be two points: its outline drawn as well as its inside.
        const std::vector<std::vector<cv::Point>> outline{pts};
        cv::fillPoly(m, outline, cv::Scalar(255));
        cv::polylines(m, outline, true, cv::Scalar(255));
        return m;
    };
    const cv::Mat ma = paint(a), mb = paint(b);
    // The tissue around the break: its median level in the box, the two lines left out.
    const cv::Mat around = inside(box) & ~ma & ~mb;
    if (cv::countNonZero(ma) == 0 || cv::countNonZero(mb) == 0 || cv::countNonZero(around) == 0)
        return false;
    const cv::Mat g = grey(box);
    const float level = percentile(g, 0.5, around);
    const cv::Mat bridge = ((g < level - depth) & inside(box)) | ma | mb;
    cv::Mat labels;
    const int n = cv::connectedComponents(bridge, labels, 8, CV_32S);
    std::vector<bool> reachedFromA(static_cast<std::size_t>(n), false);
    for (int y = 0; y < box.height; ++y)
        for (int x = 0; x < box.width; ++x)
            if (ma.at<std::uint8_t>(y, x))
                reachedFromA[static_cast<std::size_t>(labels.at<std::int32_t>(y, x))] = true;
    for (int y = 0; y < box.height; ++y)
        for (int x = 0; x < box.width; ++x)
            if (mb.at<std::uint8_t>(y, x) &&
                reachedFromA[static_cast<std::size_t>(labels.at<std::int32_t>(y, x))])
                return true;
    return false;
}
} // namespace

std::vector<cv::Point> pixelPolygon(const std::vector<cv::Point2f>& polygon, double scale) {
    std::vector<cv::Point> poly;
    poly.reserve(polygon.size());
    for (const cv::Point2f& p : polygon)
        poly.emplace_back(cvRound((p.x + 0.5) * scale - 0.5), cvRound((p.y + 0.5) * scale - 0.5));
    return poly;
}

cv::Mat polygonMask(const std::vector<cv::Point>& poly, cv::Rect box) {
    cv::Mat mask = cv::Mat::zeros(box.size(), CV_8U);
    cv::fillPoly(mask, std::vector<std::vector<cv::Point>>{poly}, cv::Scalar(255), cv::LINE_8, 0,
                 -box.tl());
    return mask;
}

void dropAlongMidline(std::vector<DamageRegion>& regions, const Midline& midline, double ringPx,
                      double maxThicknessPx) {
    if (midline.a == midline.b)
        return;
    const int ring = std::max(1, static_cast<int>(std::lround(ringPx)));
    std::erase_if(regions, [&](const DamageRegion& d) {
        if (!isGap(d) || d.polygon.size() < 3)
            return false;
        if ((d.alongVentricle || d.atCut) && reachesMidline(d.polygon, midline, ring))
            return true;
        if (d.thicknessPx > maxThicknessPx)
            return false;
        const std::vector<cv::Point> poly = pixelPolygon(d.polygon, 1.0);
        const cv::Rect box = cv::boundingRect(poly) + cv::Size(1, 1);
        return alongMidline(polygonMask(poly, box), box.tl(), midline, ring);
    });
}

std::vector<DamageRegion> continueTears(std::vector<DamageRegion>& regions,
                                        const std::vector<DamageRegion>& pieces,
                                        const cv::Mat& grey, const cv::Mat& tissue,
                                        double brainWidthPx, const DamageParams& params,
                                        double polygonScale) {
    CV_Assert(grey.type() == CV_32F && tissue.type() == CV_8U && tissue.size() == grey.size());
    std::vector<DamageRegion> joined;
    if (pieces.empty() || brainWidthPx <= 0)
        return joined;
    const double maxBreak = params.crackMinFrac * brainWidthPx;
    // The section's levels and its tissue with holes filled: whole-image passes, made only once
    // a break is short enough to look at (most pieces lie nowhere near a tear).
    struct Section {
        cv::Mat inside;
        float span = 0; ///< from the glass to the tissue level; none when not above 0
    };
    std::optional<Section> section;
    const auto joins = [&](const std::vector<cv::Point2f>& piece,
                           const std::vector<cv::Point2f>& from) {
        if (piece.empty() || from.empty())
            return false;
        const auto [p, q] = closestPoints(piece, from);
        if (cv::norm(p - q) > maxBreak)
            return false;
        if (!section) {
            const GreyLevels levels = greyLevels(grey, tissue);
            section = Section{fillHoles(tissue), levels.tissue - levels.glass};
        }
        return section->span > 0 &&
               fainterStretch(grey, section->inside, piece, from, p, q,
                              static_cast<float>(params.threadDepth) * section->span);
    };
    const auto toMask = [polygonScale](const std::vector<cv::Point2f>& poly) {
        std::vector<cv::Point2f> o;
        o.reserve(poly.size());
        for (const cv::Point2f& p : poly)
            o.emplace_back(float((p.x + 0.5) * polygonScale - 0.5),
                           float((p.y + 0.5) * polygonScale - 0.5));
        return o;
    };
    std::vector<std::vector<cv::Point2f>> pieceOutlines;
    for (const DamageRegion& d : pieces)
        pieceOutlines.push_back(toMask(d.polygon));
    std::vector<bool> taken(pieces.size(), false);
    for (DamageRegion& tear : regions) {
        if (tear.kind != DamageKind::Tear)
            continue;
        std::vector<std::vector<cv::Point2f>> frontier{toMask(tear.polygon)};
        double added = 0;
        while (!frontier.empty()) {
            const std::vector<cv::Point2f> from = std::move(frontier.back());
            frontier.pop_back();
            for (std::size_t k = 0; k < pieces.size(); ++k) {
                if (taken[k] || !joins(pieceOutlines[k], from))
                    continue;
                taken[k] = true;
                added += pieces[k].lengthPx;
                frontier.push_back(pieceOutlines[k]);
                joined.push_back(pieces[k]);
            }
        }
        tear.lengthPx += added;
    }
    return joined;
}

namespace {

/// Where a flap folded back over the tissue can lie: a straight crease is fitted (Huber) to
/// where the gap meets the tissue, and the band is the tissue within the gap's depth of that line
/// (measured square to it) along the stretch the gap spans. `farBand` is the tissue behind the
/// band (one to two depths from the line) and beside it (up to a depth past its ends). Empty
/// when the gap touches too little tissue to place a line.
cv::Mat flapBand(const cv::Mat& gap, const cv::Mat& tissue, cv::Mat& farBand) {
    cv::Mat tissueNear;
    cv::dilate(tissue, tissueNear, cv::Mat());
    std::vector<cv::Point2f> seam, all;
    for (int y = 0; y < gap.rows; ++y) {
        const std::uint8_t* g = gap.ptr<std::uint8_t>(y);
        const std::uint8_t* t = tissueNear.ptr<std::uint8_t>(y);
        for (int x = 0; x < gap.cols; ++x) {
            if (!g[x])
                continue;
            all.emplace_back(float(x), float(y));
            if (t[x])
                seam.emplace_back(float(x), float(y));
        }
    }
    if (seam.size() < 8)
        return {};
    cv::Vec4f line;
    cv::fitLine(seam, line, cv::DIST_HUBER, 0, 0.01, 0.01);
    const cv::Point2d p0(line[2], line[3]), t(line[0], line[1]);
    cv::Point2d n(-t.y, t.x); // unit normal, turned toward the gap
    double cx = 0, cy = 0;
    for (const auto& q : all)
        cx += q.x, cy += q.y;
    if ((cv::Point2d(cx / double(all.size()), cy / double(all.size())) - p0).dot(n) < 0)
        n = -n;
    // The gap's depth beyond the line and its stretch along it.
    double depth = 0, lo = 1e300, hi = -1e300;
    for (const auto& q : all) {
        const cv::Point2d d = cv::Point2d(q) - p0;
        depth = std::max(depth, d.dot(n));
        lo = std::min(lo, d.dot(t));
        hi = std::max(hi, d.dot(t));
    }
    if (depth < 1)
        return {};
    cv::Mat band = cv::Mat::zeros(gap.size(), CV_8U);
    farBand = cv::Mat::zeros(gap.size(), CV_8U);
    for (int y = 0; y < gap.rows; ++y) {
        const std::uint8_t* tm = tissue.ptr<std::uint8_t>(y);
        std::uint8_t* f = band.ptr<std::uint8_t>(y);
        std::uint8_t* fb = farBand.ptr<std::uint8_t>(y);
        for (int x = 0; x < gap.cols; ++x) {
            if (!tm[x])
                continue;
            const cv::Point2d d = cv::Point2d(x, y) - p0;
            const double side = -d.dot(n), along = d.dot(t); // side: depth into the tissue
            if (side < 0)
                continue;
            const bool within = along >= lo && along <= hi;
            if (within && side <= depth) {
                f[x] = 255;
            } else if ((within && side > depth + 2 && side <= 2 * depth + 2) ||
                       (!within && side <= depth && along >= lo - depth && along <= hi + depth)) {
                fb[x] = 255;
            }
        }
    }
    return band;
}

/// The median of `v` (reordered), which must not be empty.
float medianOf(std::vector<float>& v) {
    std::nth_element(v.begin(), v.begin() + std::ptrdiff_t(v.size() / 2), v.end());
    return v[v.size() / 2];
}

/// The level of `nearBand` over that of `farBand` above the glass, per atlas region (each with
/// at least 20 pixels in both) and combined by pixel count: 2 is tissue doubled, 1 none.
/// \return (ratio, weight: the pixels counted).
std::pair<double, double> levelRatio(const cv::Mat& grey, const cv::Mat& labels,
                                     const cv::Mat& nearBand, const cv::Mat& farBand, float glass) {
    std::map<std::int32_t, std::pair<std::vector<float>, std::vector<float>>> byRegion;
    for (int y = 0; y < grey.rows; ++y) {
        const std::uint8_t* nb = nearBand.ptr<std::uint8_t>(y);
        const std::uint8_t* fb = farBand.ptr<std::uint8_t>(y);
        const std::int32_t* lb = labels.ptr<std::int32_t>(y);
        const float* g = grey.ptr<float>(y);
        for (int x = 0; x < grey.cols; ++x) {
            if (lb[x] == 0)
                continue;
            if (nb[x])
                byRegion[lb[x]].first.push_back(g[x]);
            else if (fb[x])
                byRegion[lb[x]].second.push_back(g[x]);
        }
    }
    double weighted = 0, weight = 0;
    for (auto& [id, bands] : byRegion) {
        auto& [nearV, farV] = bands;
        if (nearV.size() < 20 || farV.size() < 20)
            continue;
        const double above = medianOf(farV) - glass;
        if (above <= 0)
            continue;
        const double count = double(std::min(nearV.size(), farV.size()));
        weighted += count * (medianOf(nearV) - glass) / above;
        weight += count;
    }
    return {weight > 0 ? weighted / weight : 0.0, weight};
}

} // namespace

std::vector<DamageRegion> foldBands(const cv::Mat& grey, const cv::Mat& tissueMask,
                                    const cv::Mat& expectedTissue, const cv::Mat& labels,
                                    double brainWidthPx, const DamageParams& params) {
    CV_Assert(grey.type() == CV_32F && tissueMask.type() == CV_8U && labels.type() == CV_32S &&
              grey.size() == tissueMask.size() && labels.size() == grey.size() &&
              expectedTissue.size() == grey.size());
    std::vector<DamageRegion> out;
    const double tissueArea = cv::countNonZero(tissueMask);
    if (tissueArea <= 0 || brainWidthPx <= 0)
        return out;
    const cv::Mat outside = ~fillHoles(tissueMask);
    if (cv::countNonZero(outside) < 64)
        return out;
    const float glass = percentile(grey, 0.5, outside);
    const cv::Mat gaps = expectedTissue & ~tissueMask;
    cv::Mat gapLabels, stats;
    const int n = labelComponents(gaps, gapLabels, stats);
    const double minLength = params.crackMinFrac * brainWidthPx;
    for (int i = 1; i < n; ++i) {
        const int w = stats.at<int>(i, cv::CC_STAT_WIDTH), h = stats.at<int>(i, cv::CC_STAT_HEIGHT);
        if (std::max(w, h) < minLength)
            continue;
        const cv::Rect bounds(stats.at<int>(i, cv::CC_STAT_LEFT), stats.at<int>(i, cv::CC_STAT_TOP),
                              w, h);
        cv::Mat dist;
        const cv::Mat whole = gapLabels == i;
        cv::distanceTransform(whole(grown(bounds, 1, grey.size())), dist, cv::DIST_L2, 3);
        double radius = 0;
        cv::minMaxLoc(dist, nullptr, &radius);
        const int depth = std::max(2, static_cast<int>(std::lround(2 * radius)));
        // A folded flap is shallow; a deeper gap is a bite or a lost lobe, not a fold.
        if (depth > 2 * params.shallowFrac * brainWidthPx)
            continue;
        const cv::Rect roi = grown(bounds, 3 * depth + 3, grey.size());
        const cv::Mat region = whole(roi);
        // Along the outline: much of its rim on the outside glass.
        cv::Mat rim;
        cv::dilate(region, rim, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(5, 5)));
        rim &= ~region;
        const double openShare =
            cv::countNonZero(rim & outside(roi)) / std::max(1.0, double(cv::countNonZero(rim)));
        if (openShare <= params.alongOutlineShare)
            continue;
        const cv::Mat tissueRoi = tissueMask(roi);
        cv::Mat nearBand, farBand;
        double ratio = 0, weight = 0;
        if (params.foldFromCrease) {
            // A flap folds about a straight crease, where the gap now meets the tissue (the
            // section's new edge), and lies over the tissue as deep as the gap reaches beyond
            // that line, along the gap's stretch.
            nearBand = flapBand(region, tissueRoi, farBand);
            if (nearBand.empty())
                continue;
        } else {
            // The band of tissue as deep as the gap along it, and the band behind that.
            cv::Mat away;
            cv::distanceTransform(~region, away, cv::DIST_L2, 3);
            const cv::Mat d1 = away <= depth + 1;
            const cv::Mat d2 = away <= 2 * depth + 1;
            nearBand = d1 & tissueRoi;
            farBand = d2 & ~d1 & tissueRoi;
        }
        std::tie(ratio, weight) = levelRatio(grey(roi), labels(roi), nearBand, farBand, glass);
        if (weight < 40 || ratio < params.foldRatio)
            continue;
        DamageRegion d;
        d.kind = DamageKind::Fold;
        // The fold is where the flap lies doubled and the place it left (glass now): both are
        // what the technician looks at; the area and share stay the doubled band's.
        d.polygon = polygonOf(nearBand | region, roi.tl());
        d.areaPx = cv::countNonZero(nearBand);
        d.share = d.areaPx / tissueArea;
        d.lengthPx = std::max(w, h);
        d.thicknessPx = depth;
        d.openShare = openShare;
        d.levelShare = ratio;
        out.push_back(std::move(d));
    }
    return out;
}

GreyLevels greyLevels(const cv::Mat& grey, const cv::Mat& tissueMask) {
    CV_Assert(grey.type() == CV_32F && tissueMask.type() == CV_8U &&
              grey.size() == tissueMask.size());
    GreyLevels out;
    const auto tissuePx = static_cast<size_t>(cv::countNonZero(tissueMask));
    if (tissuePx == 0 || tissuePx == tissueMask.total())
        return out;
    out.glass = static_cast<float>(cv::mean(grey, ~tissueMask)[0]);
    out.tissue = percentile(grey, 0.5, tissueMask);
    return out;
}

cv::Mat darkValleys(const cv::Mat& grey, GreyLevels levels, const DamageParams& params,
                    int discPx) {
    CV_Assert(grey.type() == CV_32F);
    cv::Mat sharp;
    cv::GaussianBlur(grey, sharp, cv::Size(), 0.7);
    return valleysOf(sharp, levels, params, discPx);
}

cv::Mat darkAtlasRegions(const cv::Mat& grey, const cv::Mat& labels, const cv::Mat& valid,
                         GreyLevels levels, double darkness) {
    CV_Assert(grey.type() == CV_32F && labels.type() == CV_32S && valid.type() == CV_8U &&
              labels.size() == grey.size() && valid.size() == grey.size());
    cv::Mat out = cv::Mat::zeros(labels.size(), CV_8U);
    if (levels.tissue <= levels.glass)
        return out;
    // Neighbouring pixels mostly share a label: the last one's list is kept at hand (the map's
    // elements stay where they are when it grows).
    std::unordered_map<std::int32_t, std::vector<float>> byLabel;
    std::int32_t lastId = 0;
    std::vector<float>* last = nullptr;
    for (int y = 0; y < grey.rows; ++y) {
        const float* g = grey.ptr<float>(y);
        const std::int32_t* l = labels.ptr<std::int32_t>(y);
        const std::uint8_t* v = valid.ptr<std::uint8_t>(y);
        for (int x = 0; x < grey.cols; ++x) {
            if (l[x] == 0 || !v[x])
                continue;
            if (!last || l[x] != lastId) {
                lastId = l[x];
                last = &byLabel[lastId];
            }
            last->push_back(g[x]);
        }
    }
    const float below =
        levels.glass + static_cast<float>(darkness) * (levels.tissue - levels.glass);
    std::unordered_map<std::int32_t, bool> dark;
    for (auto& [id, v] : byLabel) {
        if (kthSmallest(v, v.size() / 2) < below)
            dark[id] = true;
    }
    if (dark.empty())
        return out;
    for (int y = 0; y < labels.rows; ++y) {
        const std::int32_t* l = labels.ptr<std::int32_t>(y);
        std::uint8_t* o = out.ptr<std::uint8_t>(y);
        for (int x = 0; x < labels.cols; ++x)
            if (l[x] != 0 && dark.count(l[x]))
                o[x] = 255;
    }
    return out;
}

GapThreads gapThreads(const cv::Mat& rawGaps, const cv::Mat& openedGaps) {
    CV_Assert(rawGaps.type() == CV_8U && openedGaps.type() == CV_8U &&
              rawGaps.size() == openedGaps.size());
    GapThreads t;
    labelComponents(rawGaps & ~openedGaps, t.labels, t.stats);
    return t;
}

double crackLength(const cv::Mat& region, const GapThreads& threads) {
    CV_Assert(region.type() == CV_8U && threads.labels.size() == region.size());
    std::vector<cv::Point> piece;
    cv::findNonZero(region, piece);
    if (piece.empty())
        return 0;
    // The threads touching the region (8-connected: within one pixel of it).
    const cv::Rect box = grown(cv::boundingRect(piece), 1, region.size());
    cv::Mat near;
    cv::dilate(region(box), near, cv::Mat());
    std::vector<int> touching;
    for (int y = 0; y < box.height; ++y) {
        const std::uint8_t* n = near.ptr<std::uint8_t>(y);
        const std::int32_t* l = threads.labels.ptr<std::int32_t>(y + box.y) + box.x;
        for (int x = 0; x < box.width; ++x)
            if (n[x] && l[x] && std::find(touching.begin(), touching.end(), l[x]) == touching.end())
                touching.push_back(l[x]);
    }
    for (const int id : touching) {
        const cv::Rect b(threads.stats.at<int>(id, cv::CC_STAT_LEFT),
                         threads.stats.at<int>(id, cv::CC_STAT_TOP),
                         threads.stats.at<int>(id, cv::CC_STAT_WIDTH),
                         threads.stats.at<int>(id, cv::CC_STAT_HEIGHT));
        for (int y = b.y; y < b.y + b.height; ++y) {
            const std::int32_t* l = threads.labels.ptr<std::int32_t>(y);
            for (int x = b.x; x < b.x + b.width; ++x)
                if (l[x] == id)
                    piece.emplace_back(x, y);
        }
    }
    const cv::RotatedRect r = cv::minAreaRect(piece);
    return std::max(r.size.width, r.size.height);
}

std::vector<DamageRegion> tissueDamage(const cv::Mat& tissueMask, const AtlasExpectation& expected,
                                       double brainWidthPx, const DamageParams& params,
                                       const cv::Mat& knownFragments, const cv::Mat& grey,
                                       const cv::Mat& cutOutline) {
    const cv::Mat& expectedTissue = expected.tissue;
    const cv::Mat& expectedBrain = expected.brain;
    CV_Assert(tissueMask.type() == CV_8U && expectedTissue.size() == tissueMask.size() &&
              (grey.empty() || (grey.type() == CV_32F && grey.size() == tissueMask.size())) &&
              expectedBrain.size() == tissueMask.size() &&
              (expected.parts.empty() || expected.parts.size() == tissueMask.size()));
    std::vector<DamageRegion> out;
    const double tissueArea = std::max(1, cv::countNonZero(tissueMask));
    const double minArea = params.minRegionShare * tissueArea;

    // Gaps: the atlas expects tissue, the section shows glass. Registration slack leaves thin
    // slivers along the expected boundaries, so the expected tissue is first eroded by that
    // slack; a thin crack inside the tissue is far from those boundaries and stays.
    const int r = std::max(1, static_cast<int>(std::lround(params.slackFrac * brainWidthPx)));
    const cv::Mat disc =
        cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * r + 1, 2 * r + 1));
    cv::Mat inner;
    cv::erode(expectedTissue, inner, disc);
    const cv::Mat rawDeficit = inner & ~tissueMask;
    cv::Mat deficit;
    cv::morphologyEx(rawDeficit, deficit, cv::MORPH_OPEN,
                     cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(3, 3)));
    // A crack's thin end: what the opening removed (noise, and threads of glass) and, where the
    // grey image is known, the dark line it narrows into under a pixel wide. Looked for around
    // each tear, as far as the length of a deep tear.
    std::optional<GreyLevels> levels;
    const int reach = static_cast<int>(std::lround(params.deepTearFrac * brainWidthPx));
    const auto crackLengthOf = [&](const cv::Mat& labels, int id, const cv::Rect& box) {
        const cv::Rect roi = grown(box, reach, labels.size());
        cv::Mat thin = rawDeficit(roi).clone();
        if (!grey.empty()) {
            if (!levels)
                levels = greyLevels(grey, tissueMask);
            thin |= darkValleys(grey(roi), *levels, params) & inner(roi);
        }

        return crackLength(labels(roi) == id, gapThreads(thin, deficit(roi)));
    };
    const cv::Mat outside = ~fillHoles(tissueMask);
    // The glass the section shows inside the mapped ventricles, and within the slack of them:
    // a ventricle's own lumen.
    cv::Mat ventricleGlass;
    cv::dilate(expected.brain & ~expectedTissue, ventricleGlass, disc);
    ventricleGlass &= ~tissueMask;
    // The glass outside the section: its level and noise, to tell glass showing through a gap
    // from dim tissue (a pale fibre tract) that the tissue mask left out.
    float glassMedian = 0, glassNoise = 0, tissueMedian = 0;
    if (!grey.empty() && cv::countNonZero(outside) > 64) {
        const GlassStats glass = glassStats(grey, outside);
        glassMedian = glass.level;
        glassNoise = glass.noise;
        tissueMedian = percentile(grey, 0.5, tissueMask);
    }
    // The parts where the section has tissue: a fissure opened has tissue on both sides.
    cv::Mat tissueParts;
    if (!expected.parts.empty()) {
        tissueParts = cv::Mat::zeros(tissueMask.size(), CV_8U);
        expected.parts.copyTo(tissueParts, tissueMask);
    }
    const int ringPx =
        std::max(1, static_cast<int>(std::lround(params.fissureRingFrac * brainWidthPx)));
    cv::Mat labels, stats;
    int n = labelComponents(deficit, labels, stats);
    for (int i = 1; i < n; ++i) {
        const double area = stats.at<int>(i, cv::CC_STAT_AREA);
        if (area < minArea / 4)
            continue;
        // Each gap is looked at in its box, grown by the farthest any measure below reaches
        // (the rim, the fissure ring), so that the result is as on the whole image.
        const cv::Rect bounds(stats.at<int>(i, cv::CC_STAT_LEFT), stats.at<int>(i, cv::CC_STAT_TOP),
                              stats.at<int>(i, cv::CC_STAT_WIDTH),
                              stats.at<int>(i, cv::CC_STAT_HEIGHT));
        const cv::Rect roi = grown(bounds, std::max(r + 3, ringPx + 1), labels.size());
        const cv::Mat region = labels(roi) == i;
        std::vector<cv::Point> pts;
        cv::findNonZero(region, pts);
        const cv::RotatedRect box = cv::minAreaRect(pts);
        const double length = std::max(box.size.width, box.size.height);
        const double meanWidth = area / std::max(length, 1.0);
        // A long thin crack has little area; its length makes it count.
        if (area < minArea && length < 0.5 * params.deepTearFrac * brainWidthPx)
            continue;
        // A gap lying along the outline (much of its rim on the glass outside) and shallow is
        // registration slack where the boundary is faint, not lost tissue; a bite out of the
        // edge is deep, and a crack opens to the outside only at its mouth.
        // The rim reaches across the slack band the erosion left between gap and outline.
        cv::Mat rim = dilateEllipse(
            region, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * r + 5, 2 * r + 5)));
        rim &= ~region;
        const double rimArea = std::max(1.0, double(cv::countNonZero(rim)));
        const double openShare = cv::countNonZero(rim & outside(roi)) / rimArea;
        cv::Mat dist;
        cv::distanceTransform(region, dist, cv::DIST_L2, 3);
        double thickness = 0;
        cv::minMaxLoc(dist, nullptr, &thickness);
        const bool alongOutline = openShare > params.alongOutlineShare;
        // Where the section's own outline shows a cut (a deep asymmetric concavity, Algorithm
        // 2's damage candidates: `cutOutline`), the outline is not in doubt: a gap lying there
        // is a piece lost from the edge however shallow, and is not an outline that did not
        // bend (the section's outline turns in there, it does not run parallel). Only the
        // registration slack, already taken off, applies.
        const bool atCut = params.bitesAtCuts && !cutOutline.empty() &&
                           cv::countNonZero(region & cutOutline(roi)) >= 0.5 * area;
        const bool shallow = alongOutline && 2 * thickness < params.shallowFrac * brainWidthPx;
        // A long band along the outline, tissue along one side and glass along the other, is
        // an atlas outline lying parallel outside the section's own, a fit that did not bend
        // that far, not lost tissue: a piece lost from the edge leaves a bite about as deep as
        // it is wide, and a lobe lost whole leaves a gap with glass all round.
        const bool band =
            alongOutline && openShare < 0.75 && length >= params.bandElongation * 2 * thickness;
        if ((shallow || band) && !atCut)
            continue;
        const bool biteAtCut = shallow || band;
        // The same inside: a long band along a ventricle's lumen (much of its rim on the glass
        // the section shows in the mapped ventricle) is the ventricle's wall lying farther out
        // than the atlas's, a ventricle wider than the atlas's (enlarged, or its wall placed
        // wrong), not lost tissue; a wall torn open leaves a wedge running away from the
        // lumen, which touches it only at its mouth.
        const bool alongVentricle =
            length >= params.bandElongation * 2 * thickness &&
            cv::countNonZero(rim & ventricleGlass(roi)) > params.alongOutlineShare * rimArea;
        // Glass shows through lost tissue; a gap at a level clearly above the glass is dim tissue
        // (a pale fibre tract, unstained white matter) that the tissue mask left out.
        double levelShare = 0, levelNoiseUnits = 0;
        if (glassNoise > 0) {
            const float level = percentile(grey(roi), 0.5, region);
            levelNoiseUnits = (level - glassMedian) / glassNoise;
            levelShare = (level - glassMedian) / std::max(1e-6f, tissueMedian - glassMedian);
            if (levelNoiseUnits > params.glassNoiseUnits)
                continue;
        }
        // A gap with one part of the brain on one side and another on the other is a natural
        // fissure opened; a tear runs through a part, or across the interface.
        if (!tissueParts.empty() &&
            betweenParts(region, tissueParts(roi), ringPx, params.fissurePurity))
            continue;
        DamageRegion d;
        // A bite kept at a cut is tissue missing from the edge: its evidence is its area (a
        // tear's length is for a crack running into the tissue), and the slack band between it
        // and the expected outline was lost with it.
        d.kind = length / std::max(meanWidth, 1e-9) >= params.tearElongation && !biteAtCut
                     ? DamageKind::Tear
                     : DamageKind::Missing;
        d.atCut = biteAtCut;
        d.polygon = polygonOf(region, roi.tl());
        d.areaPx = area;
        if (biteAtCut) {
            const cv::Mat lost =
                dilateEllipse(region, disc) & expectedTissue(roi) & ~tissueMask(roi);
            d.polygon = polygonOf(lost, roi.tl());
            d.areaPx = cv::countNonZero(lost);
        }
        d.share = d.areaPx / tissueArea;
        // A crack narrows to a thread; its length runs to the thread's end.
        d.lengthPx = d.kind == DamageKind::Tear ? crackLengthOf(labels, i, bounds) : length;
        d.openShare = openShare;
        d.alongVentricle = alongVentricle;
        d.thicknessPx = 2 * thickness;
        d.levelShare = levelShare;
        d.levelNoiseUnits = levelNoiseUnits;
        out.push_back(std::move(d));
    }

    // Fragments: tissue pieces apart from the main one that lie mostly outside the mapped atlas
    // brain (a piece the atlas expects, such as a separate olfactory bulb, stays inside it).
    n = labelComponents(tissueMask, labels, stats);
    int main = 0, mainArea = 0;
    for (int i = 1; i < n; ++i)
        if (stats.at<int>(i, cv::CC_STAT_AREA) > mainArea) {
            mainArea = stats.at<int>(i, cv::CC_STAT_AREA);
            main = i;
        }
    for (int i = 1; i < n; ++i) {
        const double area = stats.at<int>(i, cv::CC_STAT_AREA);
        if (i == main || area < minArea)
            continue;
        const cv::Mat piece = labels == i;
        const double inside = cv::countNonZero(piece & expectedBrain) / area;
        const bool known =
            !knownFragments.empty() && cv::countNonZero(piece & knownFragments) > 0.5 * area;
        if (inside > 0.7 && !known)
            continue;
        DamageRegion d;
        d.kind = DamageKind::Fragment;
        d.polygon = polygonOf(piece);
        d.areaPx = area;
        d.share = area / tissueArea;
        d.lengthPx =
            std::max(stats.at<int>(i, cv::CC_STAT_WIDTH), stats.at<int>(i, cv::CC_STAT_HEIGHT));
        out.push_back(std::move(d));
    }
    std::sort(out.begin(), out.end(),
              [](const DamageRegion& a, const DamageRegion& b) { return a.areaPx > b.areaPx; });
    return out;
}

namespace {
/// Component masks of `mask` with at least `minShare` of the largest one's area, largest first.
std::vector<cv::Mat> pieces(const cv::Mat& mask, double minShare) {
    cv::Mat labels, stats;
    const int n = labelComponents(mask, labels, stats);
    std::vector<std::pair<int, int>> byArea;
    for (int i = 1; i < n; ++i)
        byArea.emplace_back(stats.at<int>(i, cv::CC_STAT_AREA), i);
    std::sort(byArea.rbegin(), byArea.rend());
    std::vector<cv::Mat> out;
    for (const auto& [area, i] : byArea)
        if (area >= minShare * byArea.front().first)
            out.push_back(labels == i);
    return out;
}
} // namespace

cv::Mat partMap(const cv::Mat& labels, const std::vector<std::vector<std::int32_t>>& parts) {
    CV_Assert(labels.type() == CV_32S && parts.size() < 256);
    std::unordered_map<std::int32_t, std::uint8_t> partOf;
    for (size_t i = 0; i < parts.size(); ++i)
        for (const std::int32_t id : parts[i])
            partOf[id] = static_cast<std::uint8_t>(i + 1);
    cv::Mat out = cv::Mat::zeros(labels.size(), CV_8U);
    // Neighbouring pixels mostly share a label: the last one's part is kept at hand.
    std::int32_t lastId = 0;
    std::uint8_t lastPart = 0;
    for (int y = 0; y < labels.rows; ++y) {
        const std::int32_t* in = labels.ptr<std::int32_t>(y);
        std::uint8_t* o = out.ptr<std::uint8_t>(y);
        for (int x = 0; x < labels.cols; ++x) {
            if (in[x] == 0)
                continue;
            if (in[x] != lastId) {
                lastId = in[x];
                const auto it = partOf.find(lastId);
                lastPart = it == partOf.end() ? 0 : it->second;
            }
            o[x] = lastPart;
        }
    }
    return out;
}

bool betweenParts(const cv::Mat& region, const cv::Mat& parts, int ringPx, double purity) {
    CV_Assert(region.type() == CV_8U && parts.type() == CV_8U && region.size() == parts.size());
    const cv::Moments m = cv::moments(region, true);
    if (m.m00 <= 0)
        return false;
    // The gap's principal axis through its centroid; the ring's pixels on either side of it.
    const double cx = m.m10 / m.m00, cy = m.m01 / m.m00;
    const double angle = 0.5 * std::atan2(2 * m.mu11, m.mu20 - m.mu02);
    const double nx = -std::sin(angle), ny = std::cos(angle);
    const cv::Rect roi = grown(cv::boundingRect(region), ringPx, region.size());
    // The region lies inside roi, so nothing beyond it is set.
    cv::Mat ring = dilateEllipse(
        region(roi).clone(),
        cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * ringPx + 1, 2 * ringPx + 1)));
    ring &= ~region(roi);
    std::array<std::array<int, 256>, 2> count{};
    int ringSide[2] = {0, 0};
    for (int y = 0; y < roi.height; ++y) {
        const std::uint8_t* rp = ring.ptr<std::uint8_t>(y);
        const std::uint8_t* pp = parts.ptr<std::uint8_t>(y + roi.y) + roi.x;
        for (int x = 0; x < roi.width; ++x) {
            if (!rp[x])
                continue;
            const int side = (x + roi.x - cx) * nx + (y + roi.y - cy) * ny > 0;
            ++ringSide[side];
            if (pp[x])
                ++count[side][pp[x]];
        }
    }
    int major[2] = {0, 0};
    for (int s = 0; s < 2; ++s) {
        int total = 0, best = 0;
        for (int k = 1; k < 256; ++k) {
            total += count[s][k];
            if (count[s][k] > best) {
                best = count[s][k];
                major[s] = k;
            }
        }
        // A side mostly glass (a bite out of the edge) has no part beside the gap.
        if (total < 0.25 * ringSide[s] || best < purity * total)
            return false;
    }
    return major[0] != major[1];
}

cv::Mat extraPieces(const cv::Mat& tissueMask, const cv::Mat& atlasMask, double minShare) {
    const auto section = pieces(tissueMask, minShare);
    const size_t expected = std::max<size_t>(1, pieces(atlasMask, minShare).size());
    if (section.size() <= expected)
        return {};
    cv::Mat extra = cv::Mat::zeros(tissueMask.size(), CV_8U);
    for (size_t i = expected; i < section.size(); ++i)
        extra |= section[i];
    return extra;
}

cv::Mat piecesInside(const cv::Mat& pieces, const cv::Mat& region, double share) {
    CV_Assert(pieces.type() == CV_8U && region.type() == CV_8U && pieces.size() == region.size());
    cv::Mat labels;
    const int n = cv::connectedComponents(pieces, labels, 8, CV_32S);
    std::vector<int> area(static_cast<size_t>(n), 0), in(static_cast<size_t>(n), 0);
    for (int y = 0; y < labels.rows; ++y) {
        const std::int32_t* l = labels.ptr<std::int32_t>(y);
        const std::uint8_t* r = region.ptr<std::uint8_t>(y);
        for (int x = 0; x < labels.cols; ++x) {
            if (l[x] == 0)
                continue;
            ++area[static_cast<size_t>(l[x])];
            if (r[x])
                ++in[static_cast<size_t>(l[x])];
        }
    }
    cv::Mat out = cv::Mat::zeros(pieces.size(), CV_8U);
    for (int y = 0; y < labels.rows; ++y) {
        const std::int32_t* l = labels.ptr<std::int32_t>(y);
        std::uint8_t* o = out.ptr<std::uint8_t>(y);
        for (int x = 0; x < labels.cols; ++x) {
            const auto k = static_cast<size_t>(l[x]);
            if (k != 0 && in[k] >= share * area[k])
                o[x] = 255;
        }
    }
    return out;
}

namespace {
/// The part of a region's evidence that the series context leaves (DamageRegion::persistence).
double novelty(const DamageRegion& region) {
    return 1.0 - std::clamp(region.persistence, 0.0, 1.0);
}
} // namespace

std::vector<DamageRegion> followedGaps(std::vector<DamageRegion> againstAffine,
                                       const std::vector<DamageRegion>& found,
                                       const cv::Mat& damagedOutline, const Midline& midline,
                                       double midlineRingPx, const DamageParams& params) {
    std::vector<DamageRegion> out;
    if (!params.followedBites || damagedOutline.empty() || againstAffine.empty())
        return out;
    CV_Assert(damagedOutline.type() == CV_8U);
    const cv::Size size = damagedOutline.size();
    cv::Mat foundGaps = cv::Mat::zeros(size, CV_8U);
    for (const DamageRegion& d : found)
        if (const std::vector<cv::Point> poly = pixelPolygon(d.polygon, 1.0);
            isGap(d) && poly.size() >= 3)
            cv::fillPoly(foundGaps, std::vector<std::vector<cv::Point>>{poly}, cv::Scalar(255));
    const cv::Rect frame(cv::Point(0, 0), size);
    for (DamageRegion& d : againstAffine) {
        // Only a gap along the outline: the outline pull and the warps follow the outline, not
        // a hole inside the tissue, which the final map's own gap pass judges.
        if (!isGap(d) || d.openShare <= params.alongOutlineShare ||
            reachesMidline(d.polygon, midline, midlineRingPx))
            continue;
        const std::vector<cv::Point> poly = pixelPolygon(d.polygon, 1.0);
        const cv::Rect box = poly.size() < 3 ? cv::Rect() : cv::boundingRect(poly) & frame;
        if (box.area() <= 0)
            continue;
        const cv::Mat mask = polygonMask(poly, box);
        const double area = cv::countNonZero(mask);
        // Where the outline is a deep asymmetric concavity (Algorithm 2): a piece lost from the
        // edge leaves one; an outline merely shaped otherwise than the atlas's does not.
        if (area <= 0 || cv::countNonZero(mask & foundGaps(box)) > 0.1 * area ||
            cv::countNonZero(mask & damagedOutline(box)) == 0)
            continue;
        d.followed = true;
        out.push_back(std::move(d));
    }
    return out;
}

double damageEvidence(const DamageRegion& region, double brainWidthPx, const DamageParams& params) {
    double e = params.damagedShare > 0 ? region.share / params.damagedShare : 0;
    if (region.kind == DamageKind::Tear && brainWidthPx > 0 && params.deepTearFrac > 0 &&
        region.lengthPx >= params.crackElongation * region.thicknessPx)
        e = std::max(e, region.lengthPx / (params.deepTearFrac * brainWidthPx));
    return e * novelty(region);
}

double scoreFromEvidence(double evidence) {
    return evidence > 0 ? 1.0 - std::exp2(-evidence) : 0.0;
}

double damageScore(std::vector<DamageRegion>& regions, double brainWidthPx,
                   const DamageParams& params) {
    double share = 0;
    double crack = 0;
    for (DamageRegion& r : regions) {
        const double e = damageEvidence(r, brainWidthPx, params);
        r.score = scoreFromEvidence(e);
        share += r.share * novelty(r);
        crack = std::max(crack, e);
    }
    const double summed = params.damagedShare > 0 ? share / params.damagedShare : 0;
    return scoreFromEvidence(std::max(summed, crack));
}

bool isDamaged(const std::vector<DamageRegion>& regions, double brainWidthPx,
               const DamageParams& params) {
    std::vector<DamageRegion> copy = regions;
    return decideDamage(copy, brainWidthPx, params).verdict == DamageVerdict::Damaged;
}

void markMisfit(std::vector<DamageRegion>& regions, const cv::Mat& tissueMask,
                const AtlasExpectation& expected, double brainWidthPx, const DamageParams& params,
                const cv::Mat& fragments, double polygonScale) {
    CV_Assert(tissueMask.type() == CV_8U && expected.tissue.size() == tissueMask.size() &&
              expected.brain.size() == tissueMask.size() &&
              (fragments.empty() || fragments.size() == tissueMask.size()));
    const cv::Size size = tissueMask.size();
    const int r = std::max(1, static_cast<int>(std::lround(params.slackFrac * brainWidthPx)));
    const auto inMasks = [&](const DamageRegion& d) {
        return pixelPolygon(d.polygon, polygonScale);
    };
    // Misplaced tissue: the section's tissue where the atlas expects none, beyond the slack
    // (the expected tissue grown by it, as the gaps are found in it shrunk by it, so that slack
    // along a boundary that fits counts on neither side). Detached pieces are damage of their
    // own, not a boundary placed wrong.
    const cv::Mat disc =
        cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * r + 1, 2 * r + 1));
    cv::Mat grownTissue, grownBrain;
    cv::dilate(expected.tissue, grownTissue, disc);
    cv::dilate(expected.brain, grownBrain, disc);
    cv::Mat excess = tissueMask & ~grownTissue;
    if (!fragments.empty())
        excess &= ~fragments;
    for (const DamageRegion& d : regions)
        if (const auto poly = inMasks(d); d.kind == DamageKind::Fragment && poly.size() >= 3) {
            // The polygon is the piece's outline; its edge pixels go with it.
            cv::fillPoly(excess, std::vector<std::vector<cv::Point>>{poly}, cv::Scalar(0));
            cv::polylines(excess, std::vector<std::vector<cv::Point>>{poly}, true, cv::Scalar(0),
                          3);
        }
    const cv::Mat inVentricle = excess & grownBrain;
    for (DamageRegion& d : regions) {
        if (!isGap(d))
            continue;
        const std::vector<cv::Point> poly = inMasks(d);
        if (poly.size() < 3)
            continue;
        // A structure placed wrong leaves its misplaced tissue across itself from the glass: a
        // hole of width w shifted by s has a crescent of glass and one of tissue, w - s apart,
        // each as long as the hole; a boundary pushed out leaves its tissue beside the band it
        // left. So within half the gap's length of it, plus the slack on either side. A crack
        // (a line of glass with tissue on both sides) is no boundary pushed out: only a thin
        // gap of the atlas (a fissure between two parts, a narrow ventricle) shifted across
        // itself leaves one, with its misplaced tissue in the mapped gap beside it: within the
        // line's width and the slack.
        const double across = d.crack ? d.thicknessPx : 0.5 * d.lengthPx;
        const int reach = static_cast<int>(std::ceil(across * polygonScale)) + 2 * r;
        const cv::Rect roi = grown(cv::boundingRect(poly), reach + 1, size);
        if (roi.area() <= 0)
            continue;
        const cv::Mat gap = polygonMask(poly, roi);
        const double gapArea = cv::countNonZero(gap);
        if (gapArea <= 0)
            continue;
        // Within `reach` of the gap: a distance transform, since the reach can be a large disc.
        cv::Mat away;
        cv::distanceTransform(~gap, away, cv::DIST_L2, cv::DIST_MASK_PRECISE);
        const cv::Mat near = away <= reach;
        d.excessShare = cv::countNonZero(near & excess(roi)) / gapArea;
        d.excessVentricleShare = cv::countNonZero(near & inVentricle(roi)) / gapArea;
        d.misfit = d.excessShare >= params.misfitExcess;
    }
}

double mirroredShare(const cv::Mat& region, const cv::Mat& atlasX, const cv::Mat& atlasY,
                     double midlineX, const cv::Mat& partner, const cv::Mat& known, int selfPx) {
    CV_Assert(region.type() == CV_8U && atlasX.type() == CV_32F && atlasY.type() == CV_32F &&
              atlasX.size() == region.size() && atlasY.size() == region.size() &&
              partner.type() == CV_8U && known.type() == CV_8U && partner.size() == known.size());
    std::vector<cv::Point> pts;
    cv::findNonZero(region, pts);
    if (pts.empty())
        return -1;
    // The region itself in atlas px, grown by the slack: a mirror image landing there is the
    // region's own (a gap across the midline).
    const cv::Size atlasSize = partner.size();
    const cv::Rect inAtlas(0, 0, atlasSize.width, atlasSize.height);
    std::vector<cv::Point> atlasPts;
    atlasPts.reserve(pts.size());
    cv::Mat self = cv::Mat::zeros(atlasSize, CV_8U);
    for (const cv::Point& p : pts) {
        const cv::Point a(cvRound(atlasX.at<float>(p)), cvRound(atlasY.at<float>(p)));
        atlasPts.push_back(a);
        if (inAtlas.contains(a))
            self.at<std::uint8_t>(a) = 255;
    }
    if (selfPx > 0)
        cv::dilate(
            self, self,
            cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * selfPx + 1, 2 * selfPx + 1)));
    int counted = 0, hit = 0;
    for (const cv::Point& a : atlasPts) {
        const cv::Point m(cvRound(2 * midlineX - a.x), a.y);
        if (!inAtlas.contains(m) || !known.at<std::uint8_t>(m) || self.at<std::uint8_t>(m))
            continue;
        ++counted;
        hit += partner.at<std::uint8_t>(m) != 0;
    }
    if (counted < 0.5 * double(pts.size()))
        return -1;
    return double(hit) / double(counted);
}

DamageDecision decideDamage(std::vector<DamageRegion>& regions, double brainWidthPx,
                            const DamageParams& params) {
    std::vector<DamageRegion> trusted;
    for (const DamageRegion& r : regions)
        if (!r.misfit)
            trusted.push_back(r);
    DamageDecision out;
    out.score = damageScore(trusted, brainWidthPx, params);
    const double all = damageScore(regions, brainWidthPx, params);
    if (out.score >= params.flagScore) {
        out.verdict = DamageVerdict::Damaged;
    } else if (all >= params.flagScore) {
        out.verdict = DamageVerdict::CheckRegistration;
        out.score = all;
    }
    return out;
}

std::string_view toString(DamageVerdict verdict) noexcept {
    switch (verdict) {
    case DamageVerdict::Clean:
        return "clean";
    case DamageVerdict::Damaged:
        return "damaged";
    case DamageVerdict::CheckRegistration:
        return "check_registration";
    }
    return "clean";
}

std::string damageSummary(const std::vector<DamageRegion>& regions) {
    if (regions.empty())
        return "no damage found";
    // Every kind, in the order of DamageKind (Chatter is the last).
    constexpr int kinds = static_cast<int>(DamageKind::Chatter) + 1;
    std::array<double, kinds> share{};
    std::array<int, kinds> count{};
    for (const DamageRegion& r : regions) {
        share[static_cast<std::size_t>(r.kind)] += r.share;
        ++count[static_cast<std::size_t>(r.kind)];
    }
    std::string s;
    for (std::size_t k = 0; k < share.size(); ++k) {
        if (!count[k])
            continue;
        char buf[96];
        std::snprintf(buf, sizeof buf, "%s%d %s (%.1f%% of the tissue)", s.empty() ? "" : ", ",
                      count[k], std::string(toString(static_cast<DamageKind>(k))).c_str(),
                      100.0 * share[k]);
        s += buf;
    }
    return s;
}

} // namespace slicestation::pipeline
