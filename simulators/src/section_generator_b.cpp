// Family B of generated sections (see section_generator_b.hpp). Written apart from
// section_generator.cpp on purpose: its own map, renderer and damage models.
#include "slicestation/sim/section_generator_b.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <array>
#include <cmath>
#include <numeric>
#include <random>
#include <string>
#include <tuple>
#include <unordered_map>

namespace slicestation::sim {
namespace {

using core::ErrorCode;
using core::makeError;

constexpr double kPi = 3.14159265358979323846;

/// splitmix64: a per-id random number that does not depend on the order ids are met in.
std::uint64_t mix(std::uint64_t x) {
    x += 0x9E3779B97F4A7C15ULL;
    x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ULL;
    x = (x ^ (x >> 27)) * 0x94D049BB133111EBULL;
    return x ^ (x >> 31);
}
double unitHash(std::uint64_t seed, std::uint64_t id, std::uint64_t salt) {
    return double(mix(seed * 0x100000001B3ULL ^ mix(id + 0x51ED27ULL * salt)) >> 11) * 0x1.0p-53;
}

struct Rng {
    std::mt19937_64 gen;
    explicit Rng(std::uint64_t seed) : gen(mix(seed ^ 0xB5A5EC7100ULL)) {}
    double uniform(double a, double b) { return std::uniform_real_distribution<double>(a, b)(gen); }
    double normal(double sd) { return std::normal_distribution<double>(0.0, sd)(gen); }
    int integer(int a, int b) { return std::uniform_int_distribution<int>(a, b)(gen); }
    bool chance(double p) { return uniform(0, 1) < p; }
};

core::Result<void> checkRange(const char* name, double v, double lo, double hi) {
    if (!std::isfinite(v) || v < lo || v > hi)
        return makeError(ErrorCode::InvalidArgument,
                         std::string("GeneratorOptionsB::") + name + " = " + std::to_string(v) +
                             " is outside [" + std::to_string(lo) + ", " + std::to_string(hi) +
                             "] or not finite");
    return {};
}

core::Result<void> validate(const cv::Mat& labels, const GeneratorOptionsB& o) {
    if (labels.empty())
        return makeError(ErrorCode::InvalidArgument, "atlas labels: empty plane");
    if (labels.type() != CV_32SC1)
        return makeError(ErrorCode::InvalidArgument, "atlas labels: must be CV_32S, one channel");
    double maxId = 0;
    cv::minMaxLoc(labels, nullptr, &maxId);
    if (maxId <= 0)
        return makeError(ErrorCode::InvalidArgument, "atlas labels: no label > 0");
    for (int side : {o.imageSize.width, o.imageSize.height})
        if (side < 300 || side > 10000)
            return makeError(
                ErrorCode::InvalidArgument,
                "GeneratorOptionsB::imageSize: each side must lie in [300, 10000], got " +
                    std::to_string(o.imageSize.width) + "x" + std::to_string(o.imageSize.height));
    const std::array<std::tuple<const char*, double, double, double>, 12> ranges{{
        {"fillFraction", o.fillFraction, 0.2, 0.95},
        {"maxRotationDeg", o.maxRotationDeg, 0, 180},
        {"maxScaleJitter", o.maxScaleJitter, 0, 0.4},
        {"maxShear", o.maxShear, 0, 0.4},
        {"maxTranslationFrac", o.maxTranslationFrac, 0, 0.4},
        {"warpAmplitudeFrac", o.warpAmplitudeFrac, 0, 0.05},
        {"swelling", o.swelling, 0, 0.2},
        {"noise", o.noise, 0, 10},
        {"texture", o.texture, 0, 3},
        {"bubbles", double(o.bubbles), -1, 20},
        {"landmarkCount", double(o.landmarkCount), 0, 100000},
        {"atlasUmPerPx", o.atlasUmPerPx, 1, 200},
    }};
    for (const auto& [name, v, lo, hi] : ranges)
        if (auto r = checkRange(name, v, lo, hi); !r)
            return r.error();
    if (o.cells.enabled)
        for (const auto& [name, v, lo, hi] :
             {std::tuple{"cells.diameterPx", o.cells.diameterPx, 1.5, 100.0},
              std::tuple{"cells.meanPerMpx", o.cells.meanPerMpx, 1.0, 1e5},
              std::tuple{"cells.contrast", o.cells.contrast, 0.05, 10.0},
              std::tuple{"cells.minDistance", o.cells.minDistance, 0.5, 3.0}})
            if (auto r = checkRange(name, v, lo, hi); !r)
                return r.error();
    if (o.stain == StainB::Template) {
        if (o.templatePlane.empty() || o.templatePlane.type() != CV_32FC1 ||
            o.templatePlane.size() != labels.size())
            return makeError(ErrorCode::InvalidArgument,
                             "GeneratorOptionsB::templatePlane: the Template stain needs a CV_32F "
                             "plane of the labels' size (" +
                                 std::to_string(labels.cols) + "x" + std::to_string(labels.rows) +
                                 ")");
        if (!cv::checkRange(o.templatePlane))
            return makeError(ErrorCode::InvalidArgument,
                             "GeneratorOptionsB::templatePlane: holds a value that is not finite");
    }
    return {};
}

/// Per-id rendering style.
struct Style {
    float level = 0; ///< stain amount in [0, 1]
    float cellsPerUm2 = 0;
    bool tract = false, ventricle = false;
};

/// Rendering choices drawn once per section.
struct SectionLook {
    bool tractsDark = false; ///< immunostain: tracts unstained (else myelin-like, bright)
    double textureStrength = 0.35;
};

Style styleOf(std::int32_t id, const core::Ontology& onto, const GeneratorOptionsB& o,
              const SectionLook& look) {
    Style s;
    const core::Structure* st = onto.find(static_cast<std::uint32_t>(id));
    if (st) {
        s.tract = onto.isDescendantOf(std::uint32_t(id), 1009);
        s.ventricle = onto.isDescendantOf(std::uint32_t(id), 73);
    } else {
        s.tract =
            std::find(o.fiberTractIds.begin(), o.fiberTractIds.end(), id) != o.fiberTractIds.end();
        s.ventricle =
            std::find(o.ventricleIds.begin(), o.ventricleIds.end(), id) != o.ventricleIds.end();
    }
    // The ontology group (e.g. Isocortex, Thalamus) shares part of the level, as a stain often
    // marks a whole system; the id's own part makes neighbours within it differ.
    const std::uint64_t group =
        st && st->path.size() > 5 ? st->path[5] : static_cast<std::uint64_t>(std::max(id, 0));
    const double own = unitHash(o.seed, std::uint64_t(id), 1);
    const double grp = unitHash(o.seed, group, 2);
    const double bimodal = own < 0.5 ? 0.1 + 0.6 * own : 0.55 + 0.9 * (own - 0.5);
    // Cells per square micrometre in a 30 um section: about 3000 per mm^2 in cortex, ten times
    // fewer and ten times more elsewhere (log-uniform), few glia in tracts.
    s.cellsPerUm2 = float(std::pow(10.0, -3.4 + 1.2 * unitHash(o.seed, std::uint64_t(id), 3)));
    switch (o.stain) {
    case StainB::Immuno:
        s.level = float(0.35 * grp + 0.65 * bimodal);
        if (s.tract)
            s.level = look.tractsDark ? 0.06f : 0.92f;
        break;
    case StainB::Nissl:
        s.level = float(0.15 + 0.85 * (std::log10(s.cellsPerUm2) + 3.4) / 1.2);
        if (s.tract) {
            s.level = 0.1f;
            s.cellsPerUm2 = 2e-4f;
        }
        break;
    case StainB::Autofluorescence:
        s.level = float(0.45 + 0.2 * grp + 0.1 * own);
        if (s.tract)
            s.level = 0.9f;
        break;
    case StainB::Template:
        s.level = 1;
        break;
    }
    if (s.tract && o.stain != StainB::Nissl)
        s.cellsPerUm2 = 2e-4f;
    return s;
}

/// Bilinear upsampling of a field sampled at p = (i * step, j * step) to every pixel.
cv::Mat upsample(const cv::Mat& coarse, int step, cv::Size size) {
    cv::Mat out(size, CV_32F);
    for (int y = 0; y < size.height; ++y) {
        const double fy = double(y) / step;
        const int y0 = std::min(int(fy), coarse.rows - 2);
        const float wy = float(fy - y0);
        const float* r0 = coarse.ptr<float>(y0);
        const float* r1 = coarse.ptr<float>(y0 + 1);
        float* o = out.ptr<float>(y);
        for (int x = 0; x < size.width; ++x) {
            const double fx = double(x) / step;
            const int x0 = std::min(int(fx), coarse.cols - 2);
            const float wx = float(fx - x0);
            o[x] = (1 - wy) * ((1 - wx) * r0[x0] + wx * r0[x0 + 1]) +
                   wy * ((1 - wx) * r1[x0] + wx * r1[x0 + 1]);
        }
    }
    return out;
}

/// Bilinear sample of a CV_32F image, clamped at the border.
double bilinear(const cv::Mat& img, double x, double y) {
    x = std::clamp(x, 0.0, img.cols - 1.001);
    y = std::clamp(y, 0.0, img.rows - 1.001);
    const int x0 = int(x), y0 = int(y);
    const double wx = x - x0, wy = y - y0;
    const float* r0 = img.ptr<float>(y0);
    const float* r1 = img.ptr<float>(std::min(y0 + 1, img.rows - 1));
    const int x1 = std::min(x0 + 1, img.cols - 1);
    return (1 - wy) * ((1 - wx) * r0[x0] + wx * r0[x1]) + wy * ((1 - wx) * r1[x0] + wx * r1[x1]);
}

/// Smooth random field in [-1, 1]-ish with features of about `scalePx`, on `size`.
cv::Mat smoothNoise(Rng& rng, cv::Size size, double scalePx) {
    const int step = std::max(2, int(scalePx / 2));
    cv::Mat c((size.height + step - 1) / step + 2, (size.width + step - 1) / step + 2, CV_32F);
    for (int y = 0; y < c.rows; ++y)
        for (int x = 0; x < c.cols; ++x)
            c.at<float>(y, x) = float(rng.normal(1.0));
    cv::GaussianBlur(c, c, cv::Size(), 1.0);
    cv::Scalar mean, sd;
    cv::meanStdDev(c, mean, sd);
    c = (c - mean[0]) / std::max(1e-6, sd[0]);
    return upsample(c, step, size);
}

/// The non-linear part d(p) of the map on a coarse grid, image px.
struct Field {
    cv::Mat dx, dy; ///< coarse, at p = (i, j) * step
    int step = 8;
    double minJacobian = 1;
};

double tpsKernel(double r2) {
    return r2 > 1e-12 ? 0.5 * r2 * std::log(r2) : 0.0;
}

Field makeField(Rng& rng, cv::Rect2d tissueBox, cv::Size size, const GeneratorOptionsB& o) {
    Field f;
    f.step = std::max(4, std::max(size.width, size.height) / 200);
    const int cols = (size.width - 1) / f.step + 2, rows = (size.height - 1) / f.step + 2;
    const double width = std::max(tissueBox.width, tissueBox.height);
    // Thin-plate spline through 4 x 4 jittered control points over the tissue's box.
    std::vector<cv::Point2d> ctrl;
    std::vector<cv::Point2d> disp;
    for (int j = 0; j < 4; ++j)
        for (int i = 0; i < 4; ++i) {
            ctrl.emplace_back(
                tissueBox.x + tissueBox.width * (i + 0.5 + rng.uniform(-0.3, 0.3)) / 4,
                tissueBox.y + tissueBox.height * (j + 0.5 + rng.uniform(-0.3, 0.3)) / 4);
            disp.emplace_back(rng.normal(o.warpAmplitudeFrac * width),
                              rng.normal(o.warpAmplitudeFrac * width));
        }
    const int n = int(ctrl.size());
    cv::Mat L = cv::Mat::zeros(n + 3, n + 3, CV_64F), rhs = cv::Mat::zeros(n + 3, 2, CV_64F);
    for (int a = 0; a < n; ++a) {
        for (int b = 0; b < n; ++b) {
            const cv::Point2d d = (ctrl[a] - ctrl[b]) * (1.0 / width);
            L.at<double>(a, b) = tpsKernel(d.dot(d));
        }
        const double row[3] = {1, (ctrl[a].x - tissueBox.x) / width,
                               (ctrl[a].y - tissueBox.y) / width};
        for (int k = 0; k < 3; ++k)
            L.at<double>(a, n + k) = L.at<double>(n + k, a) = row[k];
        rhs.at<double>(a, 0) = disp[a].x;
        rhs.at<double>(a, 1) = disp[a].y;
    }
    cv::Mat w;
    cv::solve(L, rhs, w, cv::DECOMP_SVD);
    // Local swelling under a Gaussian window and a scale gradient along one axis.
    const cv::Point2d swellCentre(tissueBox.x + tissueBox.width * rng.uniform(0.2, 0.8),
                                  tissueBox.y + tissueBox.height * rng.uniform(0.2, 0.8));
    const double swell = rng.uniform(-o.swelling, o.swelling), swellSigma = 0.25 * width;
    const double gradAngle = rng.uniform(0, 2 * kPi), grad = rng.uniform(-o.swelling, o.swelling);
    const cv::Point2d axis(std::cos(gradAngle), std::sin(gradAngle));
    const cv::Point2d centre(tissueBox.x + tissueBox.width / 2, tissueBox.y + tissueBox.height / 2);
    double gain = 1.0;
    for (int attempt = 0; attempt < 8; ++attempt) {
        f.dx.create(rows, cols, CV_32F);
        f.dy.create(rows, cols, CV_32F);
        for (int r = 0; r < rows; ++r)
            for (int c = 0; c < cols; ++c) {
                const cv::Point2d p(c * f.step, r * f.step);
                double ux = w.at<double>(n, 0) +
                            w.at<double>(n + 1, 0) * (p.x - tissueBox.x) / width +
                            w.at<double>(n + 2, 0) * (p.y - tissueBox.y) / width;
                double uy = w.at<double>(n, 1) +
                            w.at<double>(n + 1, 1) * (p.x - tissueBox.x) / width +
                            w.at<double>(n + 2, 1) * (p.y - tissueBox.y) / width;
                for (int a = 0; a < n; ++a) {
                    const cv::Point2d d = (p - ctrl[a]) * (1.0 / width);
                    const double k = tpsKernel(d.dot(d));
                    ux += w.at<double>(a, 0) * k;
                    uy += w.at<double>(a, 1) * k;
                }
                // The spline grows without bound far from its points; damp it outside the tissue.
                const cv::Point2d q = p - centre;
                const double far = std::sqrt(q.dot(q)) / width;
                const double damp = far < 0.8 ? 1.0 : std::exp(-(far - 0.8) * (far - 0.8) * 8);
                const cv::Point2d s = p - swellCentre;
                const double win = std::exp(-s.dot(s) / (2 * swellSigma * swellSigma));
                const double t = q.dot(axis) / (width / 2);
                const double along =
                    grad * t * t / 2 * (width / 2) * std::exp(-std::max(0.0, std::abs(t) - 1.2));
                f.dx.at<float>(r, c) =
                    float(gain * (damp * ux + swell * win * s.x + along * axis.x));
                f.dy.at<float>(r, c) =
                    float(gain * (damp * uy + swell * win * s.y + along * axis.y));
            }
        // Jacobian determinant of p -> p + d(p), by central differences on the grid.
        double minDet = 1e9;
        for (int r = 1; r + 1 < rows; ++r)
            for (int c = 1; c + 1 < cols; ++c) {
                const double a =
                    1 + (f.dx.at<float>(r, c + 1) - f.dx.at<float>(r, c - 1)) / (2.0 * f.step);
                const double b =
                    (f.dx.at<float>(r + 1, c) - f.dx.at<float>(r - 1, c)) / (2.0 * f.step);
                const double cc =
                    (f.dy.at<float>(r, c + 1) - f.dy.at<float>(r, c - 1)) / (2.0 * f.step);
                const double d =
                    1 + (f.dy.at<float>(r + 1, c) - f.dy.at<float>(r - 1, c)) / (2.0 * f.step);
                minDet = std::min(minDet, a * d - b * cc);
            }
        f.minJacobian = minDet;
        if (minDet >= 0.5)
            break;
        gain *= 0.6;
    }
    return f;
}

struct Damage {
    DamageKindB kind;
    cv::Mat region;   ///< CV_8U 255: tissue removed / cut off / folded away
    cv::Mat excluded; ///< CV_8U 255: also not intact (moved piece, doubled band)
    cv::Matx23d motion{1, 0, 0, 0, 1, 0};
};

/// A tissue boundary point, its outward normal (from the distance transform), and the tissue
/// centroid.
struct EdgeSite {
    cv::Point2d point, outward;
};

EdgeSite pickEdge(Rng& rng, const cv::Mat& tissue, const cv::Mat& avoid) {
    std::vector<std::vector<cv::Point>> contours;
    cv::findContours(tissue.clone(), contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_NONE);
    size_t best = 0;
    for (size_t i = 1; i < contours.size(); ++i)
        if (contours[i].size() > contours[best].size())
            best = i;
    const auto& c = contours[best];
    const cv::Moments m = cv::moments(tissue, true);
    const cv::Point2d centroid(m.m10 / std::max(1.0, m.m00), m.m01 / std::max(1.0, m.m00));
    EdgeSite s;
    for (int attempt = 0; attempt < 40; ++attempt) {
        const size_t i = size_t(rng.integer(0, int(c.size()) - 1));
        const cv::Point p = c[i];
        if (!avoid.empty() && avoid.at<std::uint8_t>(p) != 0 && attempt < 39)
            continue;
        // Outward normal from the contour's local tangent, oriented away from the centroid.
        const cv::Point a = c[(i + c.size() - 6) % c.size()], b = c[(i + 6) % c.size()];
        cv::Point2d t(b.x - a.x, b.y - a.y);
        cv::Point2d nrm(t.y, -t.x);
        const double len = std::max(1e-9, std::sqrt(nrm.dot(nrm)));
        nrm *= 1.0 / len;
        if (nrm.dot(cv::Point2d(p) - centroid) < 0)
            nrm = -nrm;
        s.point = p;
        s.outward = nrm;
        break;
    }
    return s;
}

cv::Mat crack(Rng& rng, const cv::Mat& tissue, const cv::Mat& avoid, double tissueWidth,
              double pxScale) {
    const EdgeSite e = pickEdge(rng, tissue, avoid);
    cv::Mat m = cv::Mat::zeros(tissue.size(), CV_8U);
    const double length = rng.uniform(0.2, 0.45) * tissueWidth;
    double angle = std::atan2(-e.outward.y, -e.outward.x) + rng.uniform(-0.5, 0.5);
    const double w0 = rng.uniform(2.5, 5.0) * pxScale, w1 = std::max(1.0, 1.2 * pxScale);
    cv::Point2d p = e.point + e.outward * (3 * pxScale);
    const int steps = 40;
    for (int i = 0; i < steps; ++i) {
        angle += rng.normal(0.12);
        const cv::Point2d q = p + cv::Point2d(std::cos(angle), std::sin(angle)) * (length / steps);
        const double w = w0 + (w1 - w0) * i / (steps - 1);
        cv::line(m, cv::Point(cvRound(p.x * 16), cvRound(p.y * 16)),
                 cv::Point(cvRound(q.x * 16), cvRound(q.y * 16)), cv::Scalar(255),
                 std::max(1, int(std::lround(w))), cv::LINE_8, 4);
        p = q;
    }
    return m & tissue;
}

/// An irregular blob: a disc of `radius` whose edge wobbles by a few low harmonics.
cv::Mat blob(Rng& rng, cv::Size size, cv::Point2d centre, double radius) {
    std::array<double, 4> amp{}, phase{};
    for (int k = 0; k < 4; ++k) {
        amp[size_t(k)] = rng.uniform(0, 0.18) / (k + 1);
        phase[size_t(k)] = rng.uniform(0, 2 * kPi);
    }
    std::vector<cv::Point> poly;
    for (int i = 0; i < 96; ++i) {
        const double a = 2 * kPi * i / 96;
        double r = 1;
        for (int k = 0; k < 4; ++k)
            r += amp[size_t(k)] * std::sin((k + 2) * a + phase[size_t(k)]);
        poly.emplace_back(cvRound(centre.x + radius * r * std::cos(a)),
                          cvRound(centre.y + radius * r * std::sin(a)));
    }
    cv::Mat m = cv::Mat::zeros(size, CV_8U);
    cv::fillPoly(m, std::vector<std::vector<cv::Point>>{poly}, cv::Scalar(255));
    return m;
}

/// Largest 8-connected component of a mask.
cv::Mat largestComponent(const cv::Mat& mask) {
    cv::Mat lab, stats, cents;
    const int n = cv::connectedComponentsWithStats(mask, lab, stats, cents, 8, CV_32S);
    int best = 0, bestArea = 0;
    for (int i = 1; i < n; ++i)
        if (stats.at<int>(i, cv::CC_STAT_AREA) > bestArea) {
            bestArea = stats.at<int>(i, cv::CC_STAT_AREA);
            best = i;
        }
    return best > 0 ? cv::Mat(lab == best) : cv::Mat::zeros(mask.size(), CV_8U);
}

std::vector<cv::Point2f> outline(const cv::Mat& mask) {
    std::vector<std::vector<cv::Point>> contours;
    cv::findContours(mask.clone(), contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_SIMPLE);
    size_t best = 0;
    double bestArea = -1;
    for (size_t i = 0; i < contours.size(); ++i) {
        const double a = cv::contourArea(contours[i]);
        if (a > bestArea) {
            bestArea = a;
            best = i;
        }
    }
    std::vector<cv::Point2f> out;
    if (!contours.empty())
        for (const cv::Point& p : contours[best])
            out.emplace_back(float(p.x), float(p.y));
    return out;
}

GeneratedSectionB renderB(const cv::Mat& labels, const core::Ontology& onto,
                          const GeneratorOptionsB& o) {
    Rng rng(o.seed);
    const cv::Size size = o.imageSize;
    const int W = size.width, H = size.height;
    const double pxScale = std::max(W, H) / 1500.0;

    // ---- The atlas brain and the affine part.
    const cv::Mat brain = labels > 0;
    std::vector<std::vector<cv::Point>> contours;
    cv::findContours(brain.clone(), contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_SIMPLE);
    std::vector<cv::Point2d> hull;
    for (const auto& c : contours)
        for (const auto& p : c)
            hull.emplace_back(p.x, p.y);
    const cv::Rect box = cv::boundingRect(brain);
    const cv::Point2d atlasCentre(box.x + box.width / 2.0, box.y + box.height / 2.0);

    const double rot = rng.uniform(-o.maxRotationDeg, o.maxRotationDeg) * kPi / 180;
    const double sx = 1 + rng.uniform(-o.maxScaleJitter, o.maxScaleJitter);
    const double sy = 1 + rng.uniform(-o.maxScaleJitter, o.maxScaleJitter);
    const double shear = rng.uniform(-o.maxShear, o.maxShear);
    const cv::Matx22d R(std::cos(rot), -std::sin(rot), std::sin(rot), std::cos(rot));
    const cv::Matx22d scaleShear(sx, shear, 0, sy);
    const cv::Matx22d shape = R * scaleShear; // image from atlas, before the overall scale
    double k = o.fillFraction * W / std::max(1, box.width);
    // Fit the rotated, sheared brain inside the image with a margin for the warp and damage.
    cv::Point2d lo(1e18, 1e18), hi(-1e18, -1e18);
    for (const auto& p : hull) {
        const cv::Vec2d q = shape * cv::Vec2d(p.x - atlasCentre.x, p.y - atlasCentre.y);
        lo.x = std::min(lo.x, q[0]);
        lo.y = std::min(lo.y, q[1]);
        hi.x = std::max(hi.x, q[0]);
        hi.y = std::max(hi.y, q[1]);
    }
    const double margin = 0.1;
    k = std::min({k, (1 - margin) * W / std::max(1e-9, hi.x - lo.x),
                  (1 - margin) * H / std::max(1e-9, hi.y - lo.y)});
    GeneratedSectionB out;
    cv::Mat atlasX, atlasY, imgLabels;
    Field field;
    cv::Matx23d atlasFromImage;
    for (int attempt = 0; attempt < 8; ++attempt, k *= 0.93) {
        const cv::Matx22d L = k * shape;
        // Translation: centred, then shifted by up to maxTranslationFrac as far as it fits.
        const double slackX = std::max(0.0, (W * (1 - margin) - k * (hi.x - lo.x)) / 2);
        const double slackY = std::max(0.0, (H * (1 - margin) - k * (hi.y - lo.y)) / 2);
        Rng trng(o.seed * 31 + 7);
        const double tx =
            std::clamp(trng.uniform(-1, 1) * o.maxTranslationFrac * W, -slackX, slackX);
        const double ty =
            std::clamp(trng.uniform(-1, 1) * o.maxTranslationFrac * H, -slackY, slackY);
        const cv::Point2d imgCentre(W / 2.0 - k * (lo.x + hi.x) / 2 + tx,
                                    H / 2.0 - k * (lo.y + hi.y) / 2 + ty);
        // image = L (atlas - atlasCentre) + imgCentre  =>  atlas = L^-1 (image - imgCentre) + ac
        const cv::Matx22d Li = L.inv();
        const cv::Vec2d off =
            cv::Vec2d(atlasCentre.x, atlasCentre.y) - Li * cv::Vec2d(imgCentre.x, imgCentre.y);
        atlasFromImage = cv::Matx23d(Li(0, 0), Li(0, 1), off[0], Li(1, 0), Li(1, 1), off[1]);
        const cv::Rect2d tissueBox(imgCentre.x + k * lo.x, imgCentre.y + k * lo.y,
                                   k * (hi.x - lo.x), k * (hi.y - lo.y));
        Rng frng(o.seed * 131 + 17);
        field = makeField(frng, tissueBox, size, o);
        const cv::Mat dx = upsample(field.dx, field.step, size);
        const cv::Mat dy = upsample(field.dy, field.step, size);
        atlasX.create(size, CV_32F);
        atlasY.create(size, CV_32F);
        imgLabels.create(size, CV_32S);
        bool touches = false;
        for (int y = 0; y < H; ++y) {
            const float* px = dx.ptr<float>(y);
            const float* py = dy.ptr<float>(y);
            float* ax = atlasX.ptr<float>(y);
            float* ay = atlasY.ptr<float>(y);
            std::int32_t* lab = imgLabels.ptr<std::int32_t>(y);
            for (int x = 0; x < W; ++x) {
                const double qx = x + px[x], qy = y + py[x];
                const double u =
                    atlasFromImage(0, 0) * qx + atlasFromImage(0, 1) * qy + atlasFromImage(0, 2);
                const double v =
                    atlasFromImage(1, 0) * qx + atlasFromImage(1, 1) * qy + atlasFromImage(1, 2);
                ax[x] = float(u);
                ay[x] = float(v);
                const long iu = std::lround(double(ax[x])), iv = std::lround(double(ay[x]));
                std::int32_t id = 0;
                if (iu >= 0 && iv >= 0 && iu < labels.cols && iv < labels.rows)
                    id = std::max(0, labels.at<std::int32_t>(int(iv), int(iu)));
                lab[x] = id;
                if (id > 0 && (x < 3 || y < 3 || x >= W - 3 || y >= H - 3))
                    touches = true;
            }
        }
        if (!touches)
            break;
    }
    out.truth.atlasX = atlasX;
    out.truth.atlasY = atlasY;
    out.truth.affineAtlasFromImage = atlasFromImage;
    out.truth.labelsInImage = imgLabels;
    out.minJacobian = field.minJacobian;
    const double det = std::abs(atlasFromImage(0, 0) * atlasFromImage(1, 1) -
                                atlasFromImage(0, 1) * atlasFromImage(1, 0));
    out.imageUmPerPx = o.atlasUmPerPx * std::sqrt(det);

    // ---- Styles per id and the intact stain amount S (0 = none).
    SectionLook look;
    look.tractsDark = rng.chance(0.5);
    std::unordered_map<std::int32_t, int> index;
    std::vector<Style> styles;
    cv::Mat idx(size, CV_32S);
    for (int y = 0; y < H; ++y) {
        const std::int32_t* lab = imgLabels.ptr<std::int32_t>(y);
        std::int32_t* ix = idx.ptr<std::int32_t>(y);
        for (int x = 0; x < W; ++x) {
            if (lab[x] <= 0) {
                ix[x] = -1;
                continue;
            }
            auto it = index.find(lab[x]);
            if (it == index.end()) {
                it = index.emplace(lab[x], int(styles.size())).first;
                styles.push_back(styleOf(lab[x], onto, o, look));
            }
            ix[x] = it->second;
        }
    }
    cv::Mat tissue = cv::Mat::zeros(size, CV_8U);
    cv::Mat level = cv::Mat::zeros(size, CV_32F);
    cv::Mat cells = cv::Mat::zeros(size, CV_32F);
    cv::Mat cellProb = cv::Mat::zeros(size, CV_32F);
    const double umPerPx2 = out.imageUmPerPx * out.imageUmPerPx;
    double templScale = 1;
    if (o.stain == StainB::Template) {
        std::vector<float> v;
        for (int y = 0; y < labels.rows; ++y)
            for (int x = 0; x < labels.cols; ++x)
                if (labels.at<std::int32_t>(y, x) > 0)
                    v.push_back(o.templatePlane.at<float>(y, x));
        if (!v.empty()) {
            const size_t q = std::min(v.size() - 1, size_t(0.995 * double(v.size())));
            std::nth_element(v.begin(), v.begin() + std::ptrdiff_t(q), v.end());
            templScale = 1.0 / std::max(1e-6f, v[q]);
        }
    }
    for (int y = 0; y < H; ++y) {
        const std::int32_t* ix = idx.ptr<std::int32_t>(y);
        std::uint8_t* t = tissue.ptr<std::uint8_t>(y);
        float* lv = level.ptr<float>(y);
        float* cp = cellProb.ptr<float>(y);
        float* ce = cells.ptr<float>(y);
        for (int x = 0; x < W; ++x) {
            if (ix[x] < 0)
                continue;
            const Style& s = styles[size_t(ix[x])];
            if (s.ventricle)
                continue;
            t[x] = 255;
            float l = s.level;
            if (o.stain == StainB::Template) {
                l = float(std::clamp(
                    bilinear(o.templatePlane, atlasX.at<float>(y, x), atlasY.at<float>(y, x)) *
                        templScale,
                    0.0, 1.2));
            }
            lv[x] = l;
            const float p = float(std::min(0.9, s.cellsPerUm2 * umPerPx2));
            cp[x] = p;
            if (rng.chance(p))
                ce[x] = float(rng.uniform(0.5, 1.5));
        }
    }
    // Cell bodies of about 12 um: Gaussian blobs, normalised so the mean over a region is 1.
    const double cellSigma = std::max(0.5, 6.0 / out.imageUmPerPx);
    cv::GaussianBlur(cells, cells, cv::Size(), cellSigma);
    cv::GaussianBlur(cellProb, cellProb, cv::Size(), cellSigma);
    const double texture = o.texture * (o.stain == StainB::Nissl              ? 0.6
                                        : o.stain == StainB::Immuno           ? 0.25
                                        : o.stain == StainB::Autofluorescence ? 0.2
                                                                              : 0.12);
    const cv::Mat density = smoothNoise(rng, size, 0.04 * W);
    cv::Mat S = cv::Mat::zeros(size, CV_32F);
    for (int y = 0; y < H; ++y) {
        const std::uint8_t* t = tissue.ptr<std::uint8_t>(y);
        const float* lv = level.ptr<float>(y);
        const float* ce = cells.ptr<float>(y);
        const float* cp = cellProb.ptr<float>(y);
        const float* dn = density.ptr<float>(y);
        float* s = S.ptr<float>(y);
        for (int x = 0; x < W; ++x) {
            if (!t[x])
                continue;
            const double f = std::min(3.0, double(ce[x]) / std::max(1e-4, double(cp[x])));
            s[x] = float(lv[x] * ((1 - texture) + texture * f) * (1 + 0.06 * o.texture * dn[x]));
        }
    }
    if (o.cells.enabled) {
        // Labelled cells (issue 22), on their own random stream: more stain (brighter in
        // fluorescence, darker in brightfield), over the brightest region's level.
        out.cells = placeCells(imgLabels, tissue, o.cells, o.seed);
        const cv::Mat blobs = renderCells(size, out.cells, o.cells.diameterPx);
        double maxLevel = 0;
        cv::minMaxLoc(level, nullptr, &maxLevel);
        S += blobs * (o.cells.contrast * std::max(0.2, maxLevel));
    }

    // ---- Damage, each kind once at its own place.
    const cv::Rect tbox = cv::boundingRect(tissue);
    const double tissueWidth = std::max(tbox.width, tbox.height);
    std::vector<Damage> damages;
    cv::Mat used = cv::Mat::zeros(size, CV_8U); // damage so far, grown: keep kinds apart
    auto reserve = [&](const cv::Mat& m) {
        cv::Mat grown;
        cv::dilate(m, grown, cv::getStructuringElement(cv::MORPH_ELLIPSE, {61, 61}));
        used |= grown;
    };
    if (o.damage.bite) {
        const EdgeSite e = pickEdge(rng, tissue, used);
        const double r = rng.uniform(0.06, 0.11) * tissueWidth;
        Damage d{
            DamageKindB::Bite, blob(rng, size, e.point + e.outward * (0.35 * r), r) & tissue, {}};
        d.excluded = d.region.clone();
        tissue.setTo(0, d.region);
        S.setTo(0, d.region);
        reserve(d.region);
        damages.push_back(d);
    }
    if (o.damage.crack) {
        Damage d{DamageKindB::Crack, crack(rng, tissue, used, tissueWidth, pxScale), {}};
        d.excluded = d.region.clone();
        tissue.setTo(0, d.region);
        S.setTo(0, d.region);
        reserve(d.region);
        damages.push_back(d);
    }
    if (o.damage.fold) {
        // A flap beyond a chord near the edge is folded back over the tissue: reflected about
        // the fold line, it doubles the band inside the line; the edge moves to the line.
        const EdgeSite e = pickEdge(rng, tissue, used);
        const double depth = rng.uniform(0.03, 0.06) * tissueWidth;
        const double halfLen = rng.uniform(0.1, 0.16) * tissueWidth;
        const cv::Point2d n = e.outward, lineP = e.point - n * depth, tangent(-n.y, n.x);
        Damage d{DamageKindB::Fold, cv::Mat::zeros(size, CV_8U), cv::Mat::zeros(size, CV_8U)};
        cv::Mat Snew = S.clone();
        const int reach = int(depth * 3 + 3 * halfLen);
        const cv::Rect roi = cv::Rect(cvRound(e.point.x) - reach, cvRound(e.point.y) - reach,
                                      2 * reach + 1, 2 * reach + 1) &
                             cv::Rect(0, 0, W, H);
        const double flapGain = o.brightfield ? 0.9 : 0.85;
        for (int y = roi.y; y < roi.y + roi.height; ++y)
            for (int x = roi.x; x < roi.x + roi.width; ++x) {
                const cv::Point2d p(x, y);
                const double s = (p - lineP).dot(n), lat = (p - lineP).dot(tangent);
                if (std::abs(lat) > halfLen)
                    continue;
                if (s > 0 && tissue.at<std::uint8_t>(y, x)) {
                    d.region.at<std::uint8_t>(y, x) = 255;
                    Snew.at<float>(y, x) = 0;
                }
                if (s <= 0) {
                    // The flap pixel that now lies on p.
                    const cv::Point2d q = p - n * (2 * s);
                    const int qx = cvRound(q.x), qy = cvRound(q.y);
                    if (qx < 0 || qy < 0 || qx >= W || qy >= H)
                        continue;
                    if (!tissue.at<std::uint8_t>(qy, qx) || (q - lineP).dot(n) <= 0)
                        continue;
                    d.excluded.at<std::uint8_t>(y, x) = 255;
                    Snew.at<float>(y, x) += float(flapGain * S.at<float>(qy, qx));
                }
            }
        if (cv::countNonZero(d.region) > 0) {
            S = Snew;
            // The folded flap now covers the band: it is tissue there, even over glass.
            tissue.setTo(0, d.region);
            tissue.setTo(255, d.excluded);
            d.excluded |= d.region;
            reserve(d.excluded);
            damages.push_back(d);
        }
    }
    if (o.damage.fragment) {
        const EdgeSite e = pickEdge(rng, tissue, used);
        const double r = rng.uniform(0.08, 0.13) * tissueWidth;
        cv::Mat piece = blob(rng, size, e.point + e.outward * (0.45 * r), r) & tissue;
        piece = largestComponent(piece);
        const cv::Moments m = cv::moments(piece, true);
        if (m.m00 > 20) {
            const cv::Point2d c(m.m10 / m.m00, m.m01 / m.m00);
            cv::Mat rest = tissue.clone();
            rest.setTo(0, piece);
            cv::Mat restGrown;
            cv::dilate(rest, restGrown, cv::getStructuringElement(cv::MORPH_ELLIPSE, {9, 9}));
            const double turn = rng.uniform(-35, 35);
            for (double dist = 0.5 * r; dist < 4 * r; dist += 0.25 * r) {
                const cv::Point2d to = c + e.outward * dist;
                cv::Mat M = cv::getRotationMatrix2D(c, turn, 1.0);
                M.at<double>(0, 2) += to.x - c.x;
                M.at<double>(1, 2) += to.y - c.y;
                cv::Mat moved;
                cv::warpAffine(piece, moved, M, size, cv::INTER_NEAREST);
                const cv::Rect mb = cv::boundingRect(moved);
                if (cv::countNonZero(moved) < 0.9 * m.m00 || mb.x < 4 || mb.y < 4 ||
                    mb.x + mb.width > W - 4 || mb.y + mb.height > H - 4)
                    continue;
                if (cv::countNonZero(moved & restGrown) > 0)
                    continue;
                cv::Mat Spiece = cv::Mat::zeros(size, CV_32F), Smoved;
                S.copyTo(Spiece, piece);
                cv::warpAffine(Spiece, Smoved, M, size, cv::INTER_LINEAR);
                Damage d{DamageKindB::Fragment, piece, piece | moved};
                d.motion = cv::Matx23d(M.ptr<double>());
                S.setTo(0, piece);
                tissue.setTo(0, piece);
                Smoved.copyTo(S, moved);
                tissue |= moved;
                damages.push_back(d);
                break;
            }
        }
    }
    cv::Mat damageMask = cv::Mat::zeros(size, CV_8U);
    for (const auto& d : damages) {
        const int code = d.kind == DamageKindB::Crack ? 1 : d.kind == DamageKindB::Fragment ? 3 : 2;
        damageMask.setTo(code, d.excluded);
        DamageRegion r;
        r.kind = d.kind == DamageKindB::Crack      ? DamageKind::Tear
                 : d.kind == DamageKindB::Fragment ? DamageKind::Fragment
                                                   : DamageKind::Missing;
        r.polygon = outline(d.region);
        r.areaPx = cv::countNonZero(d.region);
        r.motion = d.motion;
        out.truth.damage.push_back(r);
        out.damageKinds.push_back(d.kind);
    }
    out.truth.tissueMask = tissue;
    out.truth.damageMask = damageMask;
    markCounted(out.cells, tissue, damageMask);

    // ---- Landmarks: uniform over intact tissue at least 3 px from damage.
    {
        cv::Mat intact = tissue.clone(), near;
        cv::dilate(damageMask > 0, near, cv::getStructuringElement(cv::MORPH_ELLIPSE, {7, 7}));
        intact.setTo(0, near);
        const int stride = std::max(1, int(std::sqrt(double(cv::countNonZero(intact)) / 200000.0)));
        std::vector<cv::Point> cand;
        for (int y = 0; y < H; y += stride)
            for (int x = 0; x < W; x += stride)
                if (intact.at<std::uint8_t>(y, x))
                    cand.emplace_back(x, y);
        const int n = std::min<int>(o.landmarkCount, int(cand.size()));
        for (int i = 0; i < n; ++i) {
            const int j = rng.integer(i, int(cand.size()) - 1);
            std::swap(cand[size_t(i)], cand[size_t(j)]);
            const cv::Point p = cand[size_t(i)];
            out.truth.landmarks.push_back(
                {cv::Point2d(p.x, p.y), cv::Point2d(atlasX.at<float>(p), atlasY.at<float>(p))});
        }
    }

    // ---- Optics: blur, illumination (vignetting, scanner tiles), bubbles, noise.
    cv::GaussianBlur(S, S, cv::Size(), 0.6 * std::max(1.0, pxScale * 0.7));
    cv::Mat illum(size, CV_32F);
    const double vign = rng.uniform(0.08, 0.2);
    const int tile = int(rng.uniform(180, 340) * pxScale);
    const cv::Point2d tileOffset(rng.uniform(0, tile), rng.uniform(0, tile));
    const int tilesX = W / tile + 3, tilesY = H / tile + 3;
    std::vector<std::array<double, 3>> tileLook(size_t(tilesX * tilesY));
    for (auto& t : tileLook)
        t = {rng.uniform(-0.06, 0.06), rng.normal(0.04), rng.normal(0.04)};
    const double seam = rng.uniform(-0.08, 0.08);
    for (int y = 0; y < H; ++y) {
        float* il = illum.ptr<float>(y);
        for (int x = 0; x < W; ++x) {
            const double u = (x - W / 2.0) / (W / 2.0), v = (y - H / 2.0) / (H / 2.0);
            double g = 1 - vign * (u * u + v * v) / 2;
            if (o.tiles) {
                const double tx = (x + tileOffset.x) / tile, ty = (y + tileOffset.y) / tile;
                const int ix = int(tx), iy = int(ty);
                const auto& t =
                    tileLook[size_t(std::min(iy, tilesY - 1) * tilesX + std::min(ix, tilesX - 1))];
                // Each tile: its own gain and a linear gradient (its own vignetting).
                g *= 1 + t[0] + t[1] * (tx - ix - 0.5) + t[2] * (ty - iy - 0.5);
                const double fx = (tx - ix) * tile, fy = (ty - iy) * tile;
                if (fx < 1.0 * pxScale || fy < 1.0 * pxScale)
                    g *= 1 + seam;
            }
            il[x] = float(g);
        }
    }
    const int nBubbles = o.bubbles >= 0 ? o.bubbles : rng.integer(0, 2);
    cv::Mat bubbleRim = cv::Mat::zeros(size, CV_32F);
    for (int b = 0; b < nBubbles; ++b) {
        const cv::Point c(rng.integer(0, W - 1), rng.integer(0, H - 1));
        const int r = int(rng.uniform(0.01, 0.05) * W);
        const int thick = std::max(1, int(2 * pxScale));
        cv::circle(bubbleRim, c, r, cv::Scalar(1.0), thick, cv::LINE_AA);
        // Light passes the bubble a little dimmer inside; its rim refracts (dark).
        cv::Mat inside = cv::Mat::zeros(size, CV_8U);
        cv::circle(inside, c, r, cv::Scalar(255), cv::FILLED);
        cv::Mat dimmed;
        cv::multiply(illum, 0.95, dimmed);
        dimmed.copyTo(illum, inside);
    }
    std::normal_distribution<float> gauss(0.f, 1.f);
    if (!o.brightfield) {
        const double glass = rng.uniform(0.02, 0.06), peak = 0.85;
        const double photons = 3000 / std::max(1e-3, o.noise * o.noise);
        out.image.create(size, CV_16UC1);
        for (int y = 0; y < H; ++y) {
            const float* s = S.ptr<float>(y);
            const float* il = illum.ptr<float>(y);
            const float* rim = bubbleRim.ptr<float>(y);
            std::uint16_t* dst = out.image.ptr<std::uint16_t>(y);
            for (int x = 0; x < W; ++x) {
                double v = (glass + peak * s[x]) * il[x] * (1 - 0.5 * rim[x]);
                v += o.noise * (std::sqrt(std::max(0.0, v) / photons) * gauss(rng.gen) +
                                0.004 * gauss(rng.gen));
                dst[x] = cv::saturate_cast<std::uint16_t>(v * 50000);
            }
        }
    } else {
        // Optical densities per channel (B, G, R) of the stain and a pale counterstain.
        cv::Vec3d od = o.stain == StainB::Immuno  ? cv::Vec3d(0.78, 0.57, 0.27)  // DAB
                       : o.stain == StainB::Nissl ? cv::Vec3d(0.25, 0.85, 0.55)  // cresyl violet
                                                  : cv::Vec3d(0.35, 0.75, 0.65); // haematoxylin
        const cv::Vec3d counter(0.08, 0.12, 0.06);
        const cv::Vec3d glass(rng.uniform(225, 245), rng.uniform(228, 248), rng.uniform(225, 245));
        const double strength = rng.uniform(1.0, 1.6);
        cv::Mat tissueBlur;
        tissue.convertTo(tissueBlur, CV_32F, 1.0 / 255);
        cv::GaussianBlur(tissueBlur, tissueBlur, cv::Size(), 0.6 * std::max(1.0, pxScale * 0.7));
        out.image.create(size, CV_8UC3);
        for (int y = 0; y < H; ++y) {
            const float* s = S.ptr<float>(y);
            const float* tb = tissueBlur.ptr<float>(y);
            const float* il = illum.ptr<float>(y);
            const float* rim = bubbleRim.ptr<float>(y);
            cv::Vec3b* dst = out.image.ptr<cv::Vec3b>(y);
            for (int x = 0; x < W; ++x) {
                const double n = o.noise * 2.0 * gauss(rng.gen);
                for (int ch = 0; ch < 3; ++ch) {
                    const double a = strength * od[ch] * s[x] + counter[ch] * tb[x] + 0.6 * rim[x];
                    dst[x][ch] =
                        cv::saturate_cast<std::uint8_t>(glass[ch] * il[x] * std::exp(-a) + n);
                }
            }
        }
    }
    return out;
}

} // namespace

std::string_view toString(StainB stain) noexcept {
    switch (stain) {
    case StainB::Immuno:
        return "immuno";
    case StainB::Nissl:
        return "nissl";
    case StainB::Autofluorescence:
        return "autofluorescence";
    case StainB::Template:
        return "template";
    }
    return "?";
}

std::string_view toString(DamageKindB kind) noexcept {
    switch (kind) {
    case DamageKindB::Crack:
        return "crack";
    case DamageKindB::Bite:
        return "bite";
    case DamageKindB::Fragment:
        return "fragment";
    case DamageKindB::Fold:
        return "fold";
    }
    return "?";
}

core::Result<GeneratedSectionB> generateSectionB(const cv::Mat& atlasLabels,
                                                 const core::Ontology& ontology,
                                                 const GeneratorOptionsB& options) {
    if (auto v = validate(atlasLabels, options); !v)
        return v.error();
    try {
        return renderB(atlasLabels, ontology, options);
    } catch (const cv::Exception& e) {
        return makeError(ErrorCode::Internal, std::string("generateSectionB: OpenCV: ") + e.what());
    } catch (const std::bad_alloc&) {
        return makeError(ErrorCode::Internal, "generateSectionB: out of memory");
    }
}

} // namespace slicestation::sim
