#include "slicestation/pipeline/atlas_matching.hpp"

#include "slicestation/pipeline/affine.hpp"
#include "slicestation/pipeline/edges.hpp"
#include "slicestation/pipeline/icp.hpp"
#include "slicestation/pipeline/mask_ops.hpp"
#include "slicestation/pipeline/point_grid.hpp"
#include "slicestation/pipeline/preprocess.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <numeric>
#include <unordered_map>

namespace slicestation::pipeline {
namespace {

using core::ErrorCode;
using core::makeError;

constexpr double kPi = 3.14159265358979323846;

/// Distance (px) to the nearest non-zero pixel of `edges`.
cv::Mat distanceTo(const cv::Mat& edges) {
    cv::Mat d;
    cv::distanceTransform(edges == 0, d, cv::DIST_L2, cv::DIST_MASK_3);
    return d;
}

float lookup(const cv::Mat& dist, cv::Point2f p, float outside) {
    const int x = int(std::lround(p.x)), y = int(std::lround(p.y));
    if (x < 0 || y < 0 || x >= dist.cols || y >= dist.rows)
        return outside;
    return dist.at<float>(y, x);
}

/// OBB placement (paper section 3.2.1): centre on centre, axes on axes, per-axis or known scale.
cv::Matx23d placement(const OrientedBox& img, const OrientedBox& atl, double sMaj, double sMin,
                      bool swapAxes, double scale) {
    const cv::Vec2d aMaj = swapAxes ? atl.minor : atl.major;
    const cv::Vec2d aMin = swapAxes ? atl.major : atl.minor;
    const cv::Matx22d A(aMaj[0], aMin[0], aMaj[1], aMin[1]);
    const cv::Matx22d D(scale * sMaj, 0, 0, scale * sMin);
    const cv::Matx22d It(img.major[0], img.major[1], img.minor[0], img.minor[1]);
    const cv::Matx22d L = A * D * It;
    const cv::Vec2d c =
        cv::Vec2d(atl.centre.x, atl.centre.y) - L * cv::Vec2d(img.centre.x, img.centre.y);
    return {L(0, 0), L(0, 1), c[0], L(1, 0), L(1, 1), c[1]};
}

IcpResult runIcp(const EdgePoints& source, const EdgePoints& target, const cv::Matx23d& init,
                 const std::vector<IcpLevel>& levels, int iterations, double targetPerSource) {
    IcpResult r;
    r.targetFromSource = init;
    for (const IcpLevel& level : levels) {
        // Thinned to suit the level's reach, as in the registration: cheap and just as steady.
        const float spacing = float(std::max(1.0, level.distance / 6));
        const EdgePoints t = thinEdgePoints(target, spacing);
        const EdgePoints s = thinEdgePoints(source, float(spacing / targetPerSource));
        const PointGrid grid(t.points, float(level.distance));
        IcpOptions o;
        o.levels = {level};
        o.maxIterationsPerLevel = iterations;
        o.minMatches = 8;
        const IcpResult next = icpAffine(s, t, grid, r.targetFromSource, o);
        // A level that collapses the scale or flips the section is a wrong turn: keep the last.
        const double d0 = det(r.targetFromSource), d1 = det(next.targetFromSource);
        if (d1 <= 0 || d1 < 0.5 * d0 || d1 > 2 * d0)
            break;
        r = next;
    }
    return r;
}

double overlap(const cv::Mat& tissue, const cv::Mat& sliceMask,
               const cv::Matx23d& sliceFromSection) {
    cv::Mat mapped;
    cv::warpAffine(sliceMask, mapped, cv::Mat(sliceFromSection), tissue.size(),
                   cv::INTER_NEAREST | cv::WARP_INVERSE_MAP, cv::BORDER_CONSTANT, 0);
    const double inter = cv::countNonZero(mapped & tissue);
    const double uni = cv::countNonZero(mapped | tissue);
    return uni > 0 ? inter / uni : 0.0;
}

/// Soft agreement of edges: the mean of exp(-d^2 / 2 sigma^2) over points, d the distance to the
/// other side's nearest edge. Smooth in the slice position, so neighbouring slices rank by how
/// close their boundaries come, not by a hard tolerance.
struct Agreement {
    double sectionToSlice = 0; ///< precision: section edges explained by the slice
    double sliceToSection = 0; ///< recall: slice boundaries seen in the section
    double f() const {
        const double s = sectionToSlice + sliceToSection;
        return s > 0 ? 2 * sectionToSlice * sliceToSection / s : 0.0;
    }
};

/// Section edge points split by a side test (for the tilt); `side` returns -1, 0 (ignore) or 1.
template <class Side>
Agreement agreement(const SectionFeatures& sec, const SliceFeatures& sl, const cv::Matx23d& t,
                    Side side, int wantSide) {
    const double scale = std::sqrt(std::abs(det(t)));
    const double sigma = std::max(1.0, sl.heightPx / 90);
    const double k = -0.5 / (sigma * sigma);
    const float far = float(4 * sigma);
    Agreement a;
    double sum = 0;
    int n = 0;
    for (const cv::Point2f& p : sec.edges.points) {
        const cv::Point2f q = cv::Point2f(apply(t, p));
        if (wantSide != 0 && side(q) != wantSide)
            continue;
        const double d = lookup(sl.edgeDistance, q, far);
        sum += std::exp(k * d * d);
        ++n;
    }
    a.sectionToSlice = n > 0 ? sum / n : 0;
    const cv::Matx23d inv = invert(t);
    const double kSec = k * scale * scale; // distances measured in section px
    sum = 0;
    n = 0;
    for (const cv::Point2f& s : sl.edges.points) {
        if (wantSide != 0 && side(s) != wantSide)
            continue;
        const cv::Point2f q = cv::Point2f(apply(inv, s));
        const double d = lookup(sec.edgeDistance, q, float(far / scale));
        sum += std::exp(kSec * d * d);
        ++n;
    }
    a.sliceToSection = n > 0 ? sum / n : 0;
    return a;
}

/// Region agreement: the correlation ratio of the section's grey levels given the slice region
/// each tissue pixel falls in (1 - within-region variance / total variance). A stain makes
/// regions differ in brightness, so the slice whose regions partition the section into the most
/// uniform parts is the one it was cut from; unlike boundary distances this weighs whole areas,
/// which is what tells the frontal slices apart (their boundaries are few and mostly outline).
double regionAgreement(const SectionFeatures& sec, const SliceFeatures& sl, const cv::Matx23d& t,
                       const cv::Mat& inner) {
    if (sl.regionCount <= 0)
        return 0;
    struct Sums {
        double n = 0, s = 0, ss = 0;
    };
    std::vector<Sums> sums(size_t(sl.regionCount) + 1);
    Sums all;
    for (int y = 0; y < inner.rows; ++y) {
        const uchar* in = inner.ptr<uchar>(y);
        const float* g = sec.grey.ptr<float>(y);
        for (int x = 0; x < inner.cols; ++x) {
            if (!in[x])
                continue;
            const double qx = t(0, 0) * x + t(0, 1) * y + t(0, 2);
            const double qy = t(1, 0) * x + t(1, 1) * y + t(1, 2);
            const int ix = int(std::lround(qx)), iy = int(std::lround(qy));
            int r = 0;
            if (ix >= 0 && iy >= 0 && ix < sl.regions.cols && iy < sl.regions.rows)
                r = sl.regions.at<std::uint16_t>(iy, ix);
            Sums& b = sums[size_t(r)];
            const double v = g[x];
            b.n += 1;
            b.s += v;
            b.ss += v * v;
            all.n += 1;
            all.s += v;
            all.ss += v * v;
        }
    }
    const double total = all.ss - all.s * all.s / std::max(all.n, 1.0);
    if (all.n < 16 || total <= 0)
        return 0;
    double within = 0;
    for (const Sums& b : sums)
        if (b.n > 0)
            within += b.ss - b.s * b.s / b.n;
    return std::clamp(1 - within / total, 0.0, 1.0);
}

/// The three agreements multiply: a slice must place the tissue, explain the edges and explain
/// the grey levels by its regions. Measured on the matching benchmark (seeds 11, 12, 13, 40
/// sections each): edges x overlap alone 92.5/95/87.5% within one slice; times the region
/// agreement 100/97.5/95%.
double combinedScore(const MatchCandidate& c) {
    return c.edgeAgreement * c.overlap * c.regionAgreement;
}

/// Vertex of the parabola through (-1, a), (0, b), (1, c), in [-0.5, 0.5]; 0 when flat.
double parabolaPeak(double a, double b, double c) {
    const double den = a - 2 * b + c;
    if (den >= 0)
        return 0;
    return std::clamp(0.5 * (a - c) / den, -0.5, 0.5);
}

} // namespace

double matchWorkUmPerPx(const std::vector<cv::Mat>& labels, double umPerPx, int targetPx) {
    int longest = 1;
    for (const cv::Mat& l : labels) {
        if (l.empty())
            continue;
        const cv::Rect box = cv::boundingRect(l != 0);
        longest = std::max({longest, box.width, box.height});
    }
    return longest * umPerPx / std::max(16, targetPx);
}

SliceFeatures sliceFeatures(const cv::Mat& labels, double umPerPx, double positionUm,
                            double workUmPerPx) {
    CV_Assert(labels.type() == CV_32S && umPerPx > 0 && workUmPerPx > 0);
    SliceFeatures f;
    f.positionUm = positionUm;
    f.workUmPerPx = workUmPerPx;
    const double s = umPerPx / workUmPerPx;
    cv::Mat work;
    cv::resize(labels, work,
               cv::Size(std::max(1, int(std::lround(labels.cols * s))),
                        std::max(1, int(std::lround(labels.rows * s)))),
               0, 0, cv::INTER_NEAREST);
    f.mask = fillHoles(work != 0);
    f.areaPx = cv::countNonZero(f.mask);
    if (f.areaPx < 16)
        return f;
    const auto contour = outerContourPoints(f.mask);
    f.box = orientedBox(contour);
    f.heightPx = 2 * std::min(f.box.halfMajor, f.box.halfMinor);
    const float spacing = float(std::max(1.0, f.heightPx / 120));
    f.outline = mlsEdgePoints(contour, spacing, 3 * spacing);
    f.edges = mlsEdgePoints(labelBoundarySamples(work), spacing, 3 * spacing);
    f.edgeDistance = distanceTo(atlasEdges(work));
    // Regions renumbered densely so the region agreement can use an array per slice.
    f.regions = cv::Mat::zeros(work.size(), CV_16U);
    std::unordered_map<std::int32_t, std::uint16_t> ids;
    for (int y = 0; y < work.rows; ++y) {
        const auto* l = work.ptr<std::int32_t>(y);
        auto* r = f.regions.ptr<std::uint16_t>(y);
        for (int x = 0; x < work.cols; ++x) {
            if (l[x] == 0)
                continue;
            auto it = ids.find(l[x]);
            if (it == ids.end()) {
                if (ids.size() >= 65535)
                    continue; // more regions than any atlas plane holds
                it = ids.emplace(l[x], std::uint16_t(ids.size() + 1)).first;
            }
            r[x] = it->second;
        }
    }
    f.regionCount = int(ids.size());
    return f;
}

core::Result<SectionFeatures> sectionFeatures(const cv::Mat& image, double imageUmPerPx,
                                              double workUmPerPx, int unknownScaleMaxSide) {
    if (imageUmPerPx < 0 || workUmPerPx <= 0 || unknownScaleMaxSide < 64)
        return makeError(ErrorCode::InvalidArgument,
                         "pixel sizes must be positive and the working size at least 64 px");
    if (image.empty())
        return makeError(ErrorCode::InvalidArgument, "section image is empty");
    const int longSide = std::max(image.cols, image.rows);
    const int maxSide = imageUmPerPx > 0
                            ? std::max(64, int(std::lround(longSide * imageUmPerPx / workUmPerPx)))
                            : unknownScaleMaxSide;
    auto prepared = prepareSection(image, maxSide);
    if (!prepared)
        return prepared.error();
    SectionFeatures f;
    f.scale = prepared->scale;
    f.workUmPerPx = imageUmPerPx > 0 ? imageUmPerPx / f.scale : 0.0;
    f.grey = prepared->grey;
    f.tissue = fillHoles(prepared->tissueMask);
    f.areaPx = cv::countNonZero(f.tissue);
    const auto contour = outerContourPoints(f.tissue);
    f.box = orientedBox(contour);
    if (f.box.halfMajor <= 0)
        return makeError(ErrorCode::NoTissue, "no tissue found: the tissue outline is degenerate");
    // Algorithm 1's dominant edges, kept on and next to the tissue (as the registration does).
    cv::Mat mei = dominantEdges(f.grey);
    cv::Mat near;
    cv::dilate(prepared->tissueMask, near,
               cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(5, 5)));
    mei &= near;
    const double height = 2 * std::min(f.box.halfMajor, f.box.halfMinor);
    const float spacing = float(std::max(1.0, height / 120));
    f.outline = mlsEdgePoints(contour, spacing, 3 * spacing);
    f.edges = mlsEdgePoints(edgePixels(mei), spacing, std::max(2.f, 3 * spacing));
    // The outline counts as an edge, as the slice's outer contour does.
    cv::Mat border;
    cv::morphologyEx(f.tissue, border, cv::MORPH_GRADIENT,
                     cv::getStructuringElement(cv::MORPH_RECT, cv::Size(3, 3)));
    f.edgeDistance = distanceTo(mei | border);
    if (f.edges.size() < 20 || f.outline.size() < 20)
        return makeError(ErrorCode::NoTissue, "no tissue found: too few tissue edges to match");
    return f;
}

core::Result<SectionMatch> matchSection(const SectionFeatures& sec,
                                        const std::vector<SliceFeatures>& slices,
                                        const MatchOptions& options) {
    if (slices.empty())
        return makeError(ErrorCode::InvalidArgument, "the atlas stack is empty");
    const int last = options.last < 0 ? int(slices.size()) - 1 : options.last;
    if (options.first < 0 || last >= int(slices.size()) || options.first > last)
        return makeError(ErrorCode::InvalidArgument,
                         "slice range " + std::to_string(options.first) + ".." +
                             std::to_string(last) + " is not inside the stack (0.." +
                             std::to_string(int(slices.size()) - 1) + ")");
    std::vector<std::pair<std::string, double>> timings;

    using Clock = std::chrono::steady_clock;
    auto lap = [&m = timings, last = Clock::now()](const char* name) mutable {
        const auto now = Clock::now();
        m.emplace_back(name, std::chrono::duration<double, std::milli>(now - last).count());
        last = now;
    };
    // Stage 1, every slice: a placement refined on the outlines (paper section 3.2.1, OBB then
    // ICP), scored by tissue overlap. The OBB leaves the axis signs (and for roundish shapes
    // which axis is which) open; every slice shares the section's orientation, so the
    // alternatives are tried on every third slice only and the winner's rotation seeds the rest.
    struct Placement {
        double sMaj, sMin;
        bool swap;
    };
    auto scaleFor = [&](const SliceFeatures& sl) {
        return sec.workUmPerPx > 0 ? sec.workUmPerPx / sl.workUmPerPx
                                   : std::sqrt(sl.areaPx / std::max(sec.areaPx, 1.0));
    };
    auto usable = [&](int i) {
        const SliceFeatures& sl = slices[size_t(i)];
        return sl.areaPx >= 16 && sl.outline.size() >= 12;
    };
    auto align = [&](int i, const std::vector<cv::Matx23d>& inits) {
        const SliceFeatures& sl = slices[size_t(i)];
        const double h = sl.heightPx;
        const std::vector<IcpLevel> coarse{{30, h / 5}, {15, h / 12}};
        MatchCandidate best;
        best.index = i;
        best.overlap = -1;
        for (const cv::Matx23d& init : inits) {
            const IcpResult r = runIcp(sec.outline, sl.outline, init, coarse, 3, scaleFor(sl));
            const double o = overlap(sec.tissue, sl.mask, r.targetFromSource);
            if (o > best.overlap) {
                best.overlap = o;
                best.sliceFromSection = r.targetFromSource;
            }
        }
        return best;
    };
    std::vector<MatchCandidate> byIndex(slices.size());
    std::vector<bool> done(slices.size(), false);
    int usableCount = 0;
    for (int i = options.first; i <= last; ++i)
        usableCount += usable(i) ? 1 : 0;
    int stepsDone = 0;
    int stepsTotal = usableCount + std::min(usableCount, std::max(1, options.shortlist) + 6);
    const auto stepDone = [&] {
        if (options.progress)
            options.progress(std::min(++stepsDone, stepsTotal), stepsTotal);
    };
    MatchCandidate seed;
    seed.overlap = -1;
    for (int i = options.first; i <= last; i += 3) {
        if (!usable(i))
            continue;
        const SliceFeatures& sl = slices[size_t(i)];
        std::vector<Placement> places{{1, 1, false}, {-1, -1, false}};
        if (options.allowMirror)
            places.insert(places.end(), {{1, -1, false}, {-1, 1, false}});
        const double aspectSec = sec.box.halfMajor / std::max(sec.box.halfMinor, 1e-9);
        const double aspectSl = sl.box.halfMajor / std::max(sl.box.halfMinor, 1e-9);
        if (aspectSec < 1.25 || aspectSl < 1.25) {
            const size_t n = places.size();
            for (size_t k = 0; k < n; ++k)
                places.push_back({places[k].sMaj, -places[k].sMin, true});
        }
        std::vector<cv::Matx23d> inits;
        for (const Placement& p : places)
            inits.push_back(placement(sec.box, sl.box, p.sMaj, p.sMin, p.swap, scaleFor(sl)));
        byIndex[size_t(i)] = align(i, inits);
        done[size_t(i)] = true;
        stepDone();
        if (byIndex[size_t(i)].overlap > seed.overlap)
            seed = byIndex[size_t(i)];
    }
    if (seed.overlap < 0)
        return makeError(ErrorCode::NoTissue, "no stack slice holds a brain to match");
    // An alignment's rotation angle (of the reflection's line, doubled, when `reflected`) as its
    // unit cosine and sine.
    const auto turnOf = [](const cv::Matx23d& t, bool reflected) {
        const double c = reflected ? t(0, 0) - t(1, 1) : t(0, 0) + t(1, 1);
        const double s = reflected ? t(1, 0) + t(0, 1) : t(1, 0) - t(0, 1);
        const double n = std::max(std::hypot(c, s), 1e-12);
        return cv::Vec2d(c / n, s / n);
    };
    // The seed's rotation (and reflection) as a similarity; centre on centre with each slice's
    // own scale.
    const bool mirrored = det(seed.sliceFromSection) < 0;
    const cv::Vec2d seedTurn = turnOf(seed.sliceFromSection, mirrored);
    const double cosT = seedTurn[0], sinT = seedTurn[1];
    const auto seedInit = [&](int i) {
        const SliceFeatures& sl = slices[size_t(i)];
        const double k = scaleFor(sl);
        // Rotation, or reflection across the line at angle theta/2 when mirrored.
        const cv::Matx22d L = mirrored ? cv::Matx22d(k * cosT, k * sinT, k * sinT, -k * cosT)
                                       : cv::Matx22d(k * cosT, -k * sinT, k * sinT, k * cosT);
        const cv::Vec2d c = cv::Vec2d(sl.box.centre.x, sl.box.centre.y) -
                            L * cv::Vec2d(sec.box.centre.x, sec.box.centre.y);
        return cv::Matx23d(L(0, 0), L(0, 1), c[0], L(1, 0), L(1, 1), c[1]);
    };
    // Whether an alignment is turned (or reflected) more than 45 degrees from the seed's.
    const auto turnedFromSeed = [&](const cv::Matx23d& t) {
        return (det(t) < 0) != mirrored || turnOf(t, mirrored).dot(seedTurn) < std::cos(kPi / 4);
    };
    std::vector<MatchCandidate> all;
    for (int i = options.first; i <= last; ++i) {
        if (!usable(i))
            continue;
        if (!done[size_t(i)]) {
            byIndex[size_t(i)] = align(i, {seedInit(i)});
            stepDone();
        }
        all.push_back(byIndex[size_t(i)]);
    }
    if (all.empty())
        return makeError(ErrorCode::NoTissue, "no stack slice holds a brain to match");

    // Stage 2, a shortlist: the best overlaps and the neighbours of the top three, so the
    // position can be refined between slices.
    std::vector<size_t> order(all.size());
    std::iota(order.begin(), order.end(), size_t(0));
    std::sort(order.begin(), order.end(),
              [&](size_t a, size_t b) { return all[a].overlap > all[b].overlap; });
    std::vector<bool> chosen(all.size(), false);
    for (size_t k = 0; k < order.size() && k < size_t(std::max(1, options.shortlist)); ++k) {
        chosen[order[k]] = true;
        if (k < 3) {
            if (order[k] > 0)
                chosen[order[k] - 1] = true;
            if (order[k] + 1 < all.size())
                chosen[order[k] + 1] = true;
        }
    }
    for (const int s : options.alsoScore)
        for (size_t k = 0; k < all.size(); ++k)
            if (all[k].index == s)
                chosen[k] = true;
    cv::Mat inner;
    cv::erode(sec.tissue, inner, cv::getStructuringElement(cv::MORPH_RECT, cv::Size(3, 3)));
    // Paper section 3.2.3: ICP with normals on every edge, tightening; here only to the level
    // that decides between neighbouring slices.
    auto refine = [&](MatchCandidate& c) {
        const SliceFeatures& sl = slices[size_t(c.index)];
        const double h = sl.heightPx;
        const std::vector<IcpLevel> fine{{10, h / 10}, {8, h / 20}, {6, h / 40}};
        const double scale = std::sqrt(std::abs(det(c.sliceFromSection)));
        const IcpResult r = runIcp(sec.edges, sl.edges, c.sliceFromSection, fine, 4, scale);
        const double o = overlap(sec.tissue, sl.mask, r.targetFromSource);
        // The edge alignment may be pulled off by texture; keep whichever places the tissue
        // better, the outline alignment's overlap being the reference.
        if (o >= 0.97 * c.overlap) {
            c.sliceFromSection = r.targetFromSource;
            c.overlap = o;
        }
        const Agreement a = agreement(
            sec, sl, c.sliceFromSection, [](cv::Point2f) { return 0; }, 0);
        c.edgeAgreement = a.f();
        c.regionAgreement = regionAgreement(sec, sl, c.sliceFromSection, inner);
        c.score = combinedScore(c);
    };
    lap("overlap");
    stepsTotal = stepsDone + static_cast<int>(std::count(chosen.begin(), chosen.end(), true));
    std::vector<MatchCandidate> scored;
    for (size_t k = 0; k < all.size(); ++k) {
        if (!chosen[k])
            continue;
        const bool turned = turnedFromSeed(all[k].sliceFromSection);
        refine(all[k]);
        // A slice that tried its own placements may have taken another way up than the seed:
        // the outline of a roundish level (the olfactory bulbs) fits nearly as well turned over,
        // and its overlap chose. The section has one orientation; such a slice is scored the
        // seed's way up too, and the better score kept (the full score, not the overlap again).
        if (turned) {
            MatchCandidate seedWay = align(all[k].index, {seedInit(all[k].index)});
            refine(seedWay);
            if (seedWay.score > all[k].score)
                all[k] = seedWay;
        }
        scored.push_back(all[k]);
        stepDone();
    }
    std::sort(scored.begin(), scored.end(),
              [](const MatchCandidate& a, const MatchCandidate& b) { return a.score > b.score; });

    lap("edges");
    SectionMatch m;
    m.candidates = scored;
    const MatchCandidate& best = scored.front();
    m.index = best.index;
    m.score = best.score;
    m.positionUm = slices[size_t(best.index)].positionUm;
    auto scoreOf = [&](int index) -> double {
        for (const MatchCandidate& c : scored)
            if (c.index == index)
                return c.score;
        return -1;
    };
    const double below = scoreOf(best.index - 1), above = scoreOf(best.index + 1);
    if (below >= 0 && above >= 0) {
        const double t = parabolaPeak(below, best.score, above);
        const double step = 0.5 * (slices[size_t(best.index + 1)].positionUm -
                                   slices[size_t(best.index - 1)].positionUm);
        m.positionUm += t * step;
    }

    // Tilt: each half of the section is matched on its own against the slices around the best;
    // the difference of the halves' positions over their distance is the tilt. Only a dense
    // stack resolves the few tens of micrometres this takes.
    const int lo = std::max(options.first, best.index - 3), hi = std::min(last, best.index + 3);
    const double interval =
        hi > lo ? (slices[size_t(hi)].positionUm - slices[size_t(lo)].positionUm) / (hi - lo) : 0;
    if (options.tiltMaxIntervalUm > 0 && hi - lo >= 4 && interval > 0 &&
        interval <= options.tiltMaxIntervalUm) {
        struct Half {
            std::vector<double> score;
        };
        // Halves split at the best slice's brain centre, along columns (LR) and rows (DV).
        const SliceFeatures& ref = slices[size_t(best.index)];
        std::array<Half, 4> halves; // left, right, top, bottom
        for (int i = lo; i <= hi; ++i) {
            MatchCandidate cand;
            cand.index = i;
            const auto it = std::find_if(scored.begin(), scored.end(),
                                         [&](const MatchCandidate& s) { return s.index == i; });
            if (it != scored.end()) {
                cand = *it;
            } else {
                cand = best;
                cand.index = i;
                refine(cand);
            }
            const SliceFeatures& sl = slices[size_t(i)];
            const double sx = sl.box.centre.x, sy = sl.box.centre.y;
            auto col = [sx](cv::Point2f p) { return p.x < sx ? -1 : 1; };
            auto row = [sy](cv::Point2f p) { return p.y < sy ? -1 : 1; };
            halves[0].score.push_back(agreement(sec, sl, cand.sliceFromSection, col, -1).f());
            halves[1].score.push_back(agreement(sec, sl, cand.sliceFromSection, col, 1).f());
            halves[2].score.push_back(agreement(sec, sl, cand.sliceFromSection, row, -1).f());
            halves[3].score.push_back(agreement(sec, sl, cand.sliceFromSection, row, 1).f());
        }
        auto peak = [&](const std::vector<double>& s) {
            const size_t k = size_t(std::max_element(s.begin(), s.end()) - s.begin());
            double t = 0;
            if (k > 0 && k + 1 < s.size())
                t = parabolaPeak(s[k - 1], s[k], s[k + 1]);
            return (double(k) + t) * interval;
        };
        // The halves' centres lie about half the brain's extent apart. A plane leaning toward
        // its columns meets the right half at a smaller position (atlas_slicing.cpp's frame).
        const cv::Rect box = cv::boundingRect(ref.mask);
        const double halfWidthUm = 0.5 * box.width * ref.workUmPerPx;
        const double halfHeightUm = 0.5 * box.height * ref.workUmPerPx;
        if (halfWidthUm > 0 && halfHeightUm > 0) {
            m.tiltColumnsDeg =
                std::atan2(peak(halves[0].score) - peak(halves[1].score), halfWidthUm) * 180 / kPi;
            m.tiltRowsDeg =
                std::atan2(peak(halves[2].score) - peak(halves[3].score), halfHeightUm) * 180 / kPi;
            m.tiltEstimated = true;
        }
    }
    lap("tilt");
    m.timingsMs = std::move(timings);
    return m;
}

} // namespace slicestation::pipeline

namespace slicestation::pipeline {
namespace {

/// One slice per section, indices increasing by at least `minStep`, largest total of
/// `value[section][slice]` (slices counted from the first searched one).
std::vector<int> monotonicAssignment(const std::vector<std::vector<double>>& value, int minStep) {
    const size_t n = value.size(), m = value.front().size();
    std::vector<std::vector<double>> best(n, std::vector<double>(m, -1e300));
    std::vector<std::vector<int>> from(n, std::vector<int>(m, -1));
    best[0] = value[0];
    for (size_t i = 1; i < n; ++i) {
        // Running maximum of the previous row over j' <= j - minStep.
        double runBest = -1e300;
        int runArg = -1;
        for (size_t j = 0; j < m; ++j) {
            const long k = long(j) - minStep;
            if (k >= 0 && best[i - 1][size_t(k)] > runBest) {
                runBest = best[i - 1][size_t(k)];
                runArg = int(k);
            }
            if (runArg >= 0) {
                best[i][j] = runBest + value[i][j];
                from[i][j] = runArg;
            }
        }
    }
    std::vector<int> pick(n);
    pick[n - 1] =
        int(std::max_element(best[n - 1].begin(), best[n - 1].end()) - best[n - 1].begin());
    for (size_t i = n - 1; i > 0; --i)
        pick[i - 1] = from[i][size_t(pick[i])];
    return pick;
}

} // namespace

core::Result<std::vector<SectionMatch>> matchSeries(const std::vector<SectionFeatures>& sections,
                                                    const std::vector<SliceFeatures>& slices,
                                                    const SeriesOptions& options) {
    if (sections.empty())
        return std::vector<SectionMatch>{};
    if (slices.empty())
        return makeError(ErrorCode::InvalidArgument, "the atlas stack is empty");
    const int first = options.match.first;
    const int last = options.match.last < 0 ? int(slices.size()) - 1 : options.match.last;
    const int minStep = std::max(1, options.minStep);
    if (first < 0 || last >= int(slices.size()) || first > last)
        return makeError(ErrorCode::InvalidArgument, "slice range " + std::to_string(first) + ".." +
                                                         std::to_string(last) +
                                                         " is not inside the stack");
    const int count = last - first + 1;
    if ((int(sections.size()) - 1) * minStep + 1 > count)
        return makeError(ErrorCode::InvalidArgument,
                         std::to_string(sections.size()) + " sections " + std::to_string(minStep) +
                             " slice(s) apart do not fit in " + std::to_string(count) + " slices");

    // Raw scores per section and slice, -1 where the slice was not scored.
    std::vector<std::vector<double>> raw(sections.size(), std::vector<double>(size_t(count), -1));
    std::vector<SectionMatch> own(sections.size());
    auto merge = [&](size_t i, const SectionMatch& m) {
        for (const MatchCandidate& c : m.candidates) {
            double& r = raw[i][size_t(c.index - first)];
            r = std::max(r, c.score);
        }
    };
    auto assign = [&] {
        std::vector<std::vector<double>> value(sections.size(), std::vector<double>(size_t(count)));
        for (size_t i = 0; i < sections.size(); ++i) {
            const double top = std::max(1e-12, *std::max_element(raw[i].begin(), raw[i].end()));
            for (int j = 0; j < count; ++j)
                value[i][size_t(j)] = std::max(0.0, raw[i][size_t(j)]) / top;
        }
        return monotonicAssignment(value, minStep);
    };
    for (size_t i = 0; i < sections.size(); ++i) {
        auto m = matchSection(sections[i], slices, options.match);
        if (!m)
            return m.error();
        merge(i, *m);
        own[i] = std::move(*m);
    }
    std::vector<int> pick = assign();
    // Every slice between the neighbours' choices scored, then the programme once more.
    for (size_t i = 0; i < sections.size(); ++i) {
        MatchOptions w = options.match;
        w.first = first + (i > 0 ? pick[i - 1] + 1 : 0);
        w.last = first + (i + 1 < sections.size() ? pick[i + 1] - 1 : count - 1);
        w.first = std::min(w.first, first + pick[i]);
        w.last = std::max(w.last, first + pick[i]);
        w.shortlist = std::max(w.shortlist, w.last - w.first + 1);
        w.tiltMaxIntervalUm = 0;
        auto m = matchSection(sections[i], slices, w);
        if (m)
            merge(i, *m);
    }
    pick = assign();

    std::vector<SectionMatch> out;
    for (size_t i = 0; i < sections.size(); ++i) {
        SectionMatch m = own[i];
        const int j = pick[i];
        const bool ownChoice = m.index == first + j;
        m.index = first + j;
        m.score = std::max(0.0, raw[i][size_t(j)]);
        m.positionUm = slices[size_t(m.index)].positionUm;
        if (j > 0 && j + 1 < count && raw[i][size_t(j - 1)] >= 0 && raw[i][size_t(j + 1)] >= 0) {
            const double t = std::clamp(
                parabolaPeak(raw[i][size_t(j - 1)], m.score, raw[i][size_t(j + 1)]), -0.45, 0.45);
            m.positionUm +=
                t * 0.5 *
                (slices[size_t(m.index + 1)].positionUm - slices[size_t(m.index - 1)].positionUm);
        }
        if (!ownChoice) {
            m.tiltColumnsDeg = m.tiltRowsDeg = 0;
            m.tiltEstimated = false;
        }
        out.push_back(std::move(m));
    }
    return out;
}

} // namespace slicestation::pipeline
