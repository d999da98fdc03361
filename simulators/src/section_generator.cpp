#include "slicestation/sim/section_generator.hpp"

#include <opencv2/core.hpp>
#include <opencv2/core/utility.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <map>
#include <new>
#include <numbers>
#include <optional>
#include <random>
#include <string>

namespace slicestation::sim {

namespace {

using core::ErrorCode;
using core::makeError;

constexpr double kPi = std::numbers::pi;
constexpr int kMinImageSide = 300;
constexpr int kMaxImageSide = 10000;

// ---------------------------------------------------------------------------------------------
// Random numbers. std's distributions are implementation-defined, so everything is derived from
// raw engine output here to keep the bytes identical across standard libraries.

class Rng {
public:
    explicit Rng(std::uint64_t seed) : engine_(seed) {}
    double uniform() { return static_cast<double>(engine_() >> 11) * 0x1.0p-53; }
    double uniform(double lo, double hi) { return lo + (hi - lo) * uniform(); }
    double symmetric(double max) { return uniform(-max, max); }
    bool chance(double p) { return uniform() < p; }
    int index(int n) { return std::min(n - 1, static_cast<int>(uniform() * n)); }
    double normal() {
        const double u1 = std::max(uniform(), 1e-300), u2 = uniform();
        return std::sqrt(-2.0 * std::log(u1)) * std::cos(2.0 * kPi * u2);
    }
    std::uint64_t bits() { return engine_(); }

private:
    std::mt19937_64 engine_;
};

/// A small, fast generator for per-pixel fields. One stream per image row keeps the result
/// independent of how OpenCV splits the rows between threads.
class RowRng {
public:
    RowRng(std::uint64_t seed, int row)
        : state_(seed ^ (0x9E3779B97F4A7C15ULL * static_cast<std::uint64_t>(row + 1))) {
        next();
    }
    std::uint64_t next() {
        std::uint64_t z = (state_ += 0x9E3779B97F4A7C15ULL);
        z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ULL;
        z = (z ^ (z >> 27)) * 0x94D049BB133111EBULL;
        return z ^ (z >> 31);
    }
    float uniform() { return static_cast<float>(next() >> 40) * 0x1.0p-24f; }
    /// Two independent standard normals (Box-Muller).
    void normalPair(float& a, float& b) {
        const float u1 = std::max(uniform(), 1e-7f), u2 = uniform();
        const float r = std::sqrt(-2.0f * std::log(u1));
        a = r * std::cos(2.0f * static_cast<float>(kPi) * u2);
        b = r * std::sin(2.0f * static_cast<float>(kPi) * u2);
    }

private:
    std::uint64_t state_;
};

/// A CV_32F field of standard normal noise.
cv::Mat normalField(cv::Size size, std::uint64_t seed) {
    cv::Mat out(size, CV_32F);
    cv::parallel_for_(cv::Range(0, size.height), [&](const cv::Range& rows) {
        for (int r = rows.start; r < rows.end; ++r) {
            RowRng rng(seed, r);
            auto* p = out.ptr<float>(r);
            for (int c = 0; c < size.width; c += 2) {
                float a, b;
                rng.normalPair(a, b);
                p[c] = a;
                if (c + 1 < size.width)
                    p[c + 1] = b;
            }
        }
    });
    return out;
}

/// Smooth random field with values of about unit standard deviation; `cells` across the width.
cv::Mat smoothField(cv::Size size, int cells, Rng& rng) {
    const int cw = std::max(2, cells);
    const int ch = std::max(2, cells * size.height / std::max(1, size.width));
    cv::Mat coarse(ch + 2, cw + 2, CV_32F);
    for (int r = 0; r < coarse.rows; ++r)
        for (int c = 0; c < coarse.cols; ++c)
            coarse.at<float>(r, c) = static_cast<float>(rng.normal());
    cv::Mat out;
    cv::resize(coarse, out, size, 0, 0, cv::INTER_CUBIC);
    return out;
}

// ---------------------------------------------------------------------------------------------
// Validation

std::optional<core::Error> checkRange(const char* name, double value, double lo, double hi) {
    if (!std::isfinite(value) || value < lo || value > hi)
        return makeError(ErrorCode::InvalidArgument, std::string("GeneratorOptions::") + name +
                                                         " = " + std::to_string(value) +
                                                         " is outside [" + std::to_string(lo) +
                                                         ", " + std::to_string(hi) + "]");
    return std::nullopt;
}

std::optional<core::Error> validate(const cv::Mat& labels, const GeneratorOptions& o) {
    if (labels.empty())
        return makeError(ErrorCode::InvalidArgument, "atlas labels: the plane is empty");
    if (labels.type() != CV_32SC1)
        return makeError(ErrorCode::InvalidArgument,
                         "atlas labels: type must be CV_32SC1, got type " +
                             std::to_string(labels.type()));
    double maxLabel = 0;
    cv::minMaxLoc(labels, nullptr, &maxLabel);
    if (maxLabel <= 0)
        return makeError(ErrorCode::InvalidArgument, "atlas labels: no label > 0 (no tissue)");
    const auto side = [](int v) { return v >= kMinImageSide && v <= kMaxImageSide; };
    if (!side(o.imageSize.width) || !side(o.imageSize.height))
        return makeError(ErrorCode::InvalidArgument,
                         "GeneratorOptions::imageSize " + std::to_string(o.imageSize.width) + "x" +
                             std::to_string(o.imageSize.height) + ": each side must be in [" +
                             std::to_string(kMinImageSide) + ", " + std::to_string(kMaxImageSide) +
                             "] px");
    const std::array<std::optional<core::Error>, 8> checks = {
        checkRange("fillFraction", o.fillFraction, 0.2, 0.95),
        checkRange("maxRotationDeg", o.maxRotationDeg, 0.0, 180.0),
        checkRange("maxAnisotropy", o.maxAnisotropy, 0.0, 0.5),
        checkRange("maxShear", o.maxShear, 0.0, 0.5),
        checkRange("maxTranslationFrac", o.maxTranslationFrac, 0.0, 0.5),
        checkRange("warpAmplitudeFrac", o.warpAmplitudeFrac, 0.0, 0.1),
        checkRange("noise", o.noise, 0.0, 10.0),
        checkRange("landmarkCount", o.landmarkCount, 0, 100000),
    };
    for (const auto& c : checks)
        if (c)
            return c;
    for (const auto& c :
         {checkRange("anatomy.ventricleGrowthFrac", o.anatomy.ventricleGrowthFrac, 0.0, 0.05),
          checkRange("anatomy.fissureOpenFrac", o.anatomy.fissureOpenFrac, 0.0, 0.03)})
        if (c)
            return c;
    if (o.stain != Stain::Fluorescence && o.stain != Stain::Brightfield)
        return makeError(ErrorCode::InvalidArgument, "GeneratorOptions::stain: unknown value");
    if (o.cells.enabled)
        for (const auto& c : {checkRange("cells.diameterPx", o.cells.diameterPx, 1.5, 100.0),
                              checkRange("cells.meanPerMpx", o.cells.meanPerMpx, 1.0, 1e5),
                              checkRange("cells.contrast", o.cells.contrast, 0.05, 10.0),
                              checkRange("cells.minDistance", o.cells.minDistance, 0.5, 3.0)})
            if (c)
                return c;
    return std::nullopt;
}

// ---------------------------------------------------------------------------------------------
// The true map image -> atlas: q = A p, atlas = q + sum of Gaussian bumps around q.

struct Bump {
    cv::Point2d centre, amplitude;
    double invTwoSigma2;
};

struct TrueMap {
    cv::Matx23d atlasFromImage;
    std::vector<Bump> bumps;

    cv::Point2d operator()(double x, double y) const {
        const cv::Matx23d& a = atlasFromImage;
        const double qx = a(0, 0) * x + a(0, 1) * y + a(0, 2);
        const double qy = a(1, 0) * x + a(1, 1) * y + a(1, 2);
        return cv::Point2d(qx, qy) + displacement(qx, qy);
    }
    cv::Point2d displacement(double qx, double qy) const {
        cv::Point2d d(0, 0);
        for (const Bump& b : bumps) {
            const double dx = qx - b.centre.x, dy = qy - b.centre.y;
            d += b.amplitude * std::exp(-(dx * dx + dy * dy) * b.invTwoSigma2);
        }
        return d;
    }
};

struct AtlasTissue {
    cv::Rect box; // bounding box of labels > 0
    cv::Point2d centroid;
    std::vector<cv::Point2d> hull; // convex hull of the tissue pixels' corners
    double width = 0;              // box width, atlas px
};

AtlasTissue describeTissue(const cv::Mat& labels) {
    AtlasTissue t;
    const cv::Mat mask = labels > 0;
    t.box = cv::boundingRect(mask);
    const cv::Moments m = cv::moments(mask, true);
    t.centroid = {m.m10 / m.m00, m.m01 / m.m00};
    std::vector<cv::Point> pts;
    cv::findNonZero(mask, pts);
    std::vector<cv::Point> hull;
    cv::convexHull(pts, hull);
    for (const cv::Point& p : hull)
        for (const cv::Point2d corner : {cv::Point2d(-0.5, -0.5), cv::Point2d(0.5, -0.5),
                                         cv::Point2d(0.5, 0.5), cv::Point2d(-0.5, 0.5)})
            t.hull.push_back(cv::Point2d(p) + corner);
    t.width = t.box.width;
    return t;
}

struct Placement {
    TrueMap map;
    cv::Matx22d linear;       // atlas -> image, without translation
    double tissueWidthPx = 0; // the atlas tissue width as it appears in the image
};

Placement placeSection(const AtlasTissue& tissue, const GeneratorOptions& o, Rng& rng) {
    const double theta = rng.symmetric(o.maxRotationDeg) * kPi / 180.0;
    const double sx = 1.0 + rng.symmetric(o.maxAnisotropy);
    const double sy = 1.0 + rng.symmetric(o.maxAnisotropy);
    const double shear = rng.symmetric(o.maxShear);
    const double scaleJitter = 1.0 + rng.symmetric(0.04);
    const double tUx = rng.symmetric(1.0), tUy = rng.symmetric(1.0);

    const cv::Matx22d rot(std::cos(theta), -std::sin(theta), std::sin(theta), std::cos(theta));
    const cv::Matx22d unit = rot * cv::Matx22d(1, shear, 0, 1) * cv::Matx22d(sx, 0, 0, sy);
    const cv::Size size = o.imageSize;
    const double targetScale = o.fillFraction * size.width / tissue.width * scaleJitter;

    // Room for the warp, the soft edge and blur, and a fragment pushed outwards.
    cv::Mat sv;
    cv::SVD::compute(cv::Mat(unit), sv, cv::SVD::NO_UV);
    const double stretch = sv.at<double>(0);
    const double fragmentRoom = o.damage.fragment || o.damage.smallFragment ? 0.13 : 0.0;
    const double margin =
        8.0 + targetScale * tissue.width * (1.3 * o.warpAmplitudeFrac * stretch + fragmentRoom);

    double minX = 1e300, maxX = -1e300, minY = 1e300, maxY = -1e300;
    for (const cv::Point2d& h : tissue.hull) {
        const cv::Vec2d v = unit * cv::Vec2d(h.x - tissue.centroid.x, h.y - tissue.centroid.y);
        minX = std::min(minX, v[0]);
        maxX = std::max(maxX, v[0]);
        minY = std::min(minY, v[1]);
        maxY = std::max(maxY, v[1]);
    }
    const double roomX = size.width - 1 - 2 * margin, roomY = size.height - 1 - 2 * margin;
    const double scale =
        std::max(1e-3, std::min({targetScale, roomX / (maxX - minX), roomY / (maxY - minY)}));
    const double slackX = std::max(0.0, 0.5 * (roomX - scale * (maxX - minX)));
    const double slackY = std::max(0.0, 0.5 * (roomY - scale * (maxY - minY)));
    const double tx = tUx * std::min(o.maxTranslationFrac * size.width, slackX);
    const double ty = tUy * std::min(o.maxTranslationFrac * size.height, slackY);

    // image = L (q - centroid) + offset, with the tissue's bounding box centred on the image.
    const cv::Matx22d linear = unit * scale;
    const cv::Point2d offset(0.5 * (size.width - 1) - scale * 0.5 * (minX + maxX) + tx,
                             0.5 * (size.height - 1) - scale * 0.5 * (minY + maxY) + ty);
    const cv::Vec2d lc = linear * cv::Vec2d(tissue.centroid.x, tissue.centroid.y);
    cv::Matx23d imageFromAtlas(linear(0, 0), linear(0, 1), offset.x - lc[0], linear(1, 0),
                               linear(1, 1), offset.y - lc[1]);
    Placement p;
    cv::invertAffineTransform(imageFromAtlas, p.map.atlasFromImage);
    p.linear = linear;
    p.tissueWidthPx = scale * tissue.width;

    // Non-linear part: 4-8 Gaussian bumps, 15-35% of the tissue width wide, normalised so the
    // largest displacement over the tissue is the requested amplitude.
    const double amplitude = o.warpAmplitudeFrac * tissue.width;
    const int count = 4 + rng.index(5);
    for (int i = 0; i < count; ++i) {
        Bump b;
        b.centre = {tissue.box.x + rng.uniform() * tissue.box.width,
                    tissue.box.y + rng.uniform() * tissue.box.height};
        const double sigma = rng.uniform(0.15, 0.35) * tissue.width;
        b.invTwoSigma2 = 1.0 / (2.0 * sigma * sigma);
        const double angle = rng.uniform(0.0, 2.0 * kPi), magnitude = rng.uniform(0.4, 1.0);
        b.amplitude = {magnitude * std::cos(angle), magnitude * std::sin(angle)};
        p.map.bumps.push_back(b);
    }
    double peak = 0;
    constexpr int kGrid = 40;
    for (int i = 0; i <= kGrid; ++i)
        for (int j = 0; j <= kGrid; ++j) {
            const double qx = tissue.box.x + tissue.box.width * double(j) / kGrid;
            const double qy = tissue.box.y + tissue.box.height * double(i) / kGrid;
            peak = std::max(peak, cv::norm(p.map.displacement(qx, qy)));
        }
    double gain = peak > 0 ? amplitude / peak : 0.0;
    // |grad| of a bump peaks at |a| / sigma * exp(-1/2); keeping the sum well below 1 keeps the
    // map invertible (a diffeomorphism), at the price of a smaller amplitude for extreme options.
    double gradientBound = 0;
    for (const Bump& b : p.map.bumps)
        gradientBound +=
            gain * cv::norm(b.amplitude) * std::sqrt(2.0 * b.invTwoSigma2) * std::exp(-0.5);
    if (gradientBound > 0.5)
        gain *= 0.5 / gradientBound;
    if (gain == 0.0)
        p.map.bumps.clear();
    for (Bump& b : p.map.bumps)
        b.amplitude *= gain;
    return p;
}

void evaluateMap(const TrueMap& map, cv::Size size, cv::Mat& atlasX, cv::Mat& atlasY) {
    atlasX.create(size, CV_32F);
    atlasY.create(size, CV_32F);
    cv::parallel_for_(cv::Range(0, size.height), [&](const cv::Range& rows) {
        for (int r = rows.start; r < rows.end; ++r) {
            auto* px = atlasX.ptr<float>(r);
            auto* py = atlasY.ptr<float>(r);
            for (int c = 0; c < size.width; ++c) {
                const cv::Point2d q = map(c, r);
                px[c] = static_cast<float>(q.x);
                py[c] = static_cast<float>(q.y);
            }
        }
    });
}

// ---------------------------------------------------------------------------------------------
// The stain: per-region looks rendered in atlas space, then seen through the map.

struct RegionLook {
    float level = 0;   // base intensity (fluorescence) or stain density (brightfield), ~0.3-0.8
    float density = 0; // relative cell density
    float gradX = 0, gradY = 0; // relative change across the tissue width
    bool empty = false;         // ventricle: no tissue
};

bool contains(const std::vector<std::int32_t>& ids, std::int32_t id) {
    return std::find(ids.begin(), ids.end(), id) != ids.end();
}

std::map<std::int32_t, RegionLook> makeLooks(const cv::Mat& labels, const GeneratorOptions& o,
                                             Rng& rng) {
    std::map<std::int32_t, RegionLook> looks;
    for (int r = 0; r < labels.rows; ++r) {
        const auto* p = labels.ptr<std::int32_t>(r);
        std::int32_t last = 0;
        for (int c = 0; c < labels.cols; ++c)
            if (p[c] > 0 && p[c] != last)
                looks[last = p[c]] = {};
    }
    // Real stains leave some neighbouring regions almost indistinguishable: a third of the
    // regions copy the level of an earlier one.
    std::vector<float> levels;
    for (auto& [id, look] : looks) {
        if (!levels.empty() && rng.chance(0.35))
            look.level = levels[static_cast<size_t>(rng.index(static_cast<int>(levels.size())))] +
                         static_cast<float>(rng.symmetric(0.03));
        else
            look.level = static_cast<float>(rng.uniform(0.35, 0.8));
        levels.push_back(look.level);
        look.density = static_cast<float>(rng.uniform(0.6, 1.4));
        const double g = rng.uniform(0.0, 0.25), a = rng.uniform(0.0, 2.0 * kPi);
        look.gradX = static_cast<float>(g * std::cos(a));
        look.gradY = static_cast<float>(g * std::sin(a));
    }
    const bool tractsBright = rng.chance(0.5);
    for (auto& [id, look] : looks) {
        if (contains(o.fiberTractIds, id)) {
            look.level = tractsBright ? 1.15f : 0.2f;
            look.density = 0.35f;
        }
        if (contains(o.ventricleIds, id))
            look.empty = true;
    }
    return looks;
}

struct AtlasMaps {
    cv::Mat level, density, coverage; // CV_32F, atlas size
};

AtlasMaps renderAtlasMaps(const cv::Mat& labels, const std::map<std::int32_t, RegionLook>& looks,
                          const AtlasTissue& tissue) {
    AtlasMaps m;
    m.level.create(labels.size(), CV_32F);
    m.density.create(labels.size(), CV_32F);
    m.coverage.create(labels.size(), CV_32F);
    double sumLevel = 0;
    for (const auto& [id, look] : looks)
        sumLevel += look.level;
    const float meanLevel = looks.empty() ? 0.5f : static_cast<float>(sumLevel / looks.size());
    for (int r = 0; r < labels.rows; ++r) {
        const auto* lp = labels.ptr<std::int32_t>(r);
        auto* level = m.level.ptr<float>(r);
        auto* density = m.density.ptr<float>(r);
        auto* coverage = m.coverage.ptr<float>(r);
        const float v = static_cast<float>((r - tissue.centroid.y) / tissue.width);
        for (int c = 0; c < labels.cols; ++c) {
            const auto it = lp[c] > 0 ? looks.find(lp[c]) : looks.end();
            if (it == looks.end() || it->second.empty) {
                // Outside values only matter at the soft edge: keep them neutral.
                level[c] = meanLevel;
                density[c] = 1.0f;
                coverage[c] = 0.0f;
                continue;
            }
            const RegionLook& look = it->second;
            const float u = static_cast<float>((c - tissue.centroid.x) / tissue.width);
            level[c] = look.level * (1.0f + look.gradX * u + look.gradY * v);
            density[c] = look.density;
            coverage[c] = 1.0f;
        }
    }
    // Atlas planes are pixel staircases; a little smoothing keeps the magnified outline round.
    for (cv::Mat* mat : {&m.level, &m.density, &m.coverage})
        cv::GaussianBlur(*mat, *mat, cv::Size(), 0.6);
    return m;
}

cv::Mat seeThroughMap(const cv::Mat& atlasImage, const cv::Mat& atlasX, const cv::Mat& atlasY,
                      int interpolation, double border) {
    cv::Mat out;
    cv::remap(atlasImage, out, atlasX, atlasY, interpolation, cv::BORDER_CONSTANT,
              cv::Scalar(border));
    return out;
}

// ---------------------------------------------------------------------------------------------
// Damage, painted on image-space layers.

struct Layers {
    cv::Mat coverage; // CV_32F 0..1, how much tissue covers the pixel
    cv::Mat signal;   // CV_32F, stain where covered
    cv::Mat nuclei;   // CV_32F, nuclear texture (about 1 at a nucleus' centre)
    cv::Mat level;    // CV_32F, the region's stain level with its slow variations
    cv::Mat labelled; // CV_32F, labelled cells (GeneratorOptions::cells) or empty
    cv::Mat tissue;   // CV_8U 255 tissue present (no ventricles)
    cv::Mat outline;  // CV_8U 255 inside the section's outline (ventricles included)
    /// CV_8U 255 where coverage > 0: the outline plus the soft edge around it. Damage clears
    /// all of it, or a faint line of the old edge would stay behind.
    cv::Mat support;
};

cv::Mat largestComponent(const cv::Mat& mask) {
    cv::Mat labels, stats, centroids;
    const int n = cv::connectedComponentsWithStats(mask, labels, stats, centroids, 8, CV_32S);
    int best = 0, bestArea = 0;
    for (int i = 1; i < n; ++i)
        if (stats.at<int>(i, cv::CC_STAT_AREA) > bestArea) {
            bestArea = stats.at<int>(i, cv::CC_STAT_AREA);
            best = i;
        }
    return best > 0 ? cv::Mat(labels == best) : cv::Mat(cv::Mat::zeros(mask.size(), CV_8U));
}

std::vector<cv::Point2f> outlineOf(const cv::Mat& mask) {
    std::vector<std::vector<cv::Point>> contours;
    cv::findContours(mask.clone(), contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_SIMPLE);
    std::vector<cv::Point2f> out;
    size_t best = 0;
    double bestArea = -1;
    for (size_t i = 0; i < contours.size(); ++i) {
        const double a = cv::contourArea(contours[i]);
        if (a > bestArea) {
            bestArea = a;
            best = i;
        }
    }
    if (!contours.empty())
        for (const cv::Point& p : contours[best])
            out.emplace_back(float(p.x), float(p.y));
    return out;
}

/// The outermost outline point seen from `centre` along `dir`.
cv::Point2d boundaryPoint(const cv::Mat& outline, cv::Point2d centre, cv::Point2d dir) {
    const double far = std::hypot(outline.cols, outline.rows);
    for (double t = far; t > 0; t -= 0.5) {
        const cv::Point2d p = centre + dir * t;
        const int x = cvRound(p.x), y = cvRound(p.y);
        if (x >= 0 && y >= 0 && x < outline.cols && y < outline.rows &&
            outline.at<std::uint8_t>(y, x))
            return p;
    }
    return centre;
}

struct DamageContext {
    cv::Point2d centre; // of the section, image px
    double size = 0;    // tissue width, image px
    cv::Matx22d linear; // atlas -> image, to pick directions in anatomical terms
};

cv::Point2d imageDirection(const DamageContext& ctx, double atlasAngle) {
    const cv::Vec2d d = ctx.linear * cv::Vec2d(std::cos(atlasAngle), std::sin(atlasAngle));
    const double n = std::hypot(d[0], d[1]);
    return {d[0] / n, d[1] / n};
}

cv::Mat tearMask(const Layers& layers, const DamageContext& ctx, double atlasAngle, Rng& rng) {
    const cv::Point2d out = imageDirection(ctx, atlasAngle);
    const cv::Point2d mouth = boundaryPoint(layers.outline, ctx.centre, out);
    const double length = rng.uniform(0.15, 0.35) * ctx.size;
    const double width = rng.uniform(0.02, 0.06) * ctx.size;
    const double outside = 0.03 * ctx.size; // start outside so the crack opens cleanly
    double heading = std::atan2(-out.y, -out.x) + rng.symmetric(20.0) * kPi / 180.0;
    constexpr int kSteps = 40;
    const double step = (length + outside) / kSteps;
    cv::Point2d p = mouth - cv::Point2d(std::cos(heading), std::sin(heading)) * outside;
    std::vector<cv::Point> left, right;
    double turn = 0;
    for (int i = 0; i <= kSteps; ++i) {
        const double along = std::max(0.0, i * step - outside) / length;
        const double w =
            0.5 * width * std::pow(std::max(0.0, 1.0 - along), 1.3) * (1.0 + rng.symmetric(0.15));
        const cv::Point2d n(-std::sin(heading), std::cos(heading));
        left.emplace_back(cvRound(p.x + n.x * w), cvRound(p.y + n.y * w));
        right.emplace_back(cvRound(p.x - n.x * w), cvRound(p.y - n.y * w));
        // A smoothly wandering crack: the turn rate itself does a small random walk.
        turn = 0.8 * turn + rng.symmetric(0.06);
        heading += turn;
        p += cv::Point2d(std::cos(heading), std::sin(heading)) * step;
    }
    std::vector<cv::Point> polygon(left);
    polygon.insert(polygon.end(), right.rbegin(), right.rend());
    cv::Mat mask = cv::Mat::zeros(layers.outline.size(), CV_8U);
    cv::fillPoly(mask, std::vector<std::vector<cv::Point>>{polygon}, cv::Scalar(255));
    return mask;
}

cv::Mat missingMask(const Layers& layers, const DamageContext& ctx, double atlasAngle, Rng& rng) {
    const cv::Point2d out = imageDirection(ctx, atlasAngle);
    const cv::Point2d centre = boundaryPoint(layers.outline, ctx.centre, out);
    const double radius = rng.uniform(0.05, 0.12) * ctx.size;
    std::array<double, 3> amp{}, phase{};
    for (size_t k = 0; k < amp.size(); ++k) {
        amp[k] = rng.uniform(0.0, 0.1);
        phase[k] = rng.uniform(0.0, 2.0 * kPi);
    }
    std::vector<cv::Point> polygon;
    constexpr int kVertices = 96;
    for (int i = 0; i < kVertices; ++i) {
        const double a = 2.0 * kPi * i / kVertices;
        double r = radius;
        for (size_t k = 0; k < amp.size(); ++k)
            r *= 1.0 + amp[k] * std::cos(static_cast<double>(k + 2) * a + phase[k]);
        polygon.emplace_back(cvRound(centre.x + r * std::cos(a)),
                             cvRound(centre.y + r * std::sin(a)));
    }
    cv::Mat mask = cv::Mat::zeros(layers.outline.size(), CV_8U);
    cv::fillPoly(mask, std::vector<std::vector<cv::Point>>{polygon}, cv::Scalar(255));
    return mask;
}

struct Fragment {
    cv::Mat piece;       // where it was, soft edge included
    cv::Mat pieceTissue; // the same inside the outline only
    cv::Mat moved;       // where the piece is, soft edge included
    cv::Matx23d motion;
};

/// Cuts a cap of `minFraction` to `maxFraction` of the section off along a wavy line and pushes
/// it outwards until it is clear of the rest. Returns nothing when no placement inside the image
/// works.
std::optional<Fragment> fragmentAt(const Layers& layers, const DamageContext& ctx,
                                   double atlasAngle, Rng& rng, double minFraction = 0.05,
                                   double maxFraction = 0.10) {
    const cv::Point2d n = imageDirection(ctx, atlasAngle);
    const cv::Point2d t(-n.y, n.x);
    const double fraction = rng.uniform(minFraction, maxFraction);
    const double wave = 0.02 * ctx.size, waveLength = rng.uniform(0.25, 0.45) * ctx.size;
    const double wavePhase = rng.uniform(0.0, 2.0 * kPi);
    const cv::Mat& outline = layers.outline;
    cv::Mat score(outline.size(), CV_32F, cv::Scalar(-1e9f));
    std::vector<float> values; // of the outline's pixels: the fraction is of the tissue
    for (int r = 0; r < outline.rows; ++r) {
        const auto* o = outline.ptr<std::uint8_t>(r);
        const auto* sup = layers.support.ptr<std::uint8_t>(r);
        auto* s = score.ptr<float>(r);
        for (int c = 0; c < outline.cols; ++c) {
            if (!sup[c])
                continue;
            const cv::Point2d d = cv::Point2d(c, r) - ctx.centre;
            s[c] = static_cast<float>(d.dot(n) +
                                      wave * std::sin(2 * kPi * d.dot(t) / waveLength + wavePhase));
            if (o[c])
                values.push_back(s[c]);
        }
    }
    if (values.empty())
        return std::nullopt;
    const size_t k = static_cast<size_t>((1.0 - fraction) * static_cast<double>(values.size()));
    std::nth_element(values.begin(), values.begin() + static_cast<std::ptrdiff_t>(k), values.end());
    const cv::Mat piece = largestComponent(score > values[k]);
    const cv::Mat pieceTissue = piece & outline;
    const cv::Moments m = cv::moments(pieceTissue, true);
    if (m.m00 < 1)
        return std::nullopt;
    const cv::Point2d pc(m.m10 / m.m00, m.m01 / m.m00);
    const cv::Mat rest = layers.support & ~piece;
    const double angle = (rng.chance(0.5) ? 1 : -1) * rng.uniform(2.0, 5.0);
    double distance = rng.uniform(0.03, 0.08) * ctx.size;
    const cv::Mat kernel = cv::getStructuringElement(cv::MORPH_ELLIPSE, {9, 9});
    for (int attempt = 0; attempt < 30; ++attempt, distance += 0.01 * ctx.size) {
        cv::Matx23d motion = cv::getRotationMatrix2D(pc, angle, 1.0);
        motion(0, 2) += n.x * distance;
        motion(1, 2) += n.y * distance;
        cv::Mat moved;
        cv::warpAffine(piece, moved, motion, piece.size(), cv::INTER_NEAREST, cv::BORDER_CONSTANT,
                       cv::Scalar(0));
        const cv::Rect box = cv::boundingRect(moved);
        const cv::Rect inner(4, 4, outline.cols - 8, outline.rows - 8);
        if (cv::countNonZero(moved) < 0.9 * m.m00 || (box & inner) != box)
            return std::nullopt;
        cv::Mat grown;
        cv::dilate(moved, grown, kernel);
        if (cv::countNonZero(grown & rest) == 0)
            return Fragment{piece, pieceTissue, moved, motion};
    }
    return std::nullopt;
}

void moveFragment(Layers& layers, const Fragment& fr, GroundTruth& truth);

/// Clears the tissue under `shape` (glass shows) and records it as damage of `kind`.
void removeTissue(Layers& layers, const cv::Mat& shape, DamageKind kind, std::uint8_t code,
                  GroundTruth& truth) {
    const cv::Mat removed = shape & layers.outline;
    const int area = cv::countNonZero(removed);
    if (area == 0)
        return;
    DamageRegion region{kind, outlineOf(removed), static_cast<double>(area), {1, 0, 0, 0, 1, 0}};
    truth.damage.push_back(std::move(region));
    truth.damageMask.setTo(code, removed);
    const cv::Mat cleared = shape & layers.support;
    layers.coverage.setTo(0.0f, cleared);
    layers.support.setTo(0, cleared);
    layers.tissue.setTo(0, removed);
    layers.outline.setTo(0, removed);
}

/// Paints the requested damage on `layers` and records it in `truth`.
void paintDamage(Layers& layers, const DamageContext& ctx, const GeneratorOptions& o, Rng& rng,
                 GroundTruth& truth) {
    if (!o.damage.tear && !o.damage.missing && !o.damage.fragment)
        return;
    // Spread the kinds around the section; atlas angle 0 points to the atlas' right side, so
    // angles near 0 or pi are lateral (a tear there is on one hemisphere only).
    constexpr double kDeg = kPi / 180.0;
    const double side = rng.chance(0.5) ? 0.0 : kPi;
    const double tearAngle = side + rng.symmetric(40.0) * kDeg;
    const double fragmentAngle = (kPi - side) + rng.symmetric(40.0) * kDeg;
    const double missingAngle =
        (rng.chance(0.5) ? 90.0 : -90.0) * kDeg + rng.symmetric(25.0) * kDeg;

    const auto removeFrom = [&](const cv::Mat& shape, DamageKind kind, std::uint8_t code) {
        removeTissue(layers, shape, kind, code, truth);
    };
    if (o.damage.tear)
        removeFrom(tearMask(layers, ctx, tearAngle, rng), DamageKind::Tear, 1);
    if (o.damage.missing)
        removeFrom(missingMask(layers, ctx, missingAngle, rng), DamageKind::Missing, 2);
    if (o.damage.fragment) {
        std::optional<Fragment> f;
        for (int attempt = 0; attempt < 8 && !f; ++attempt)
            f = fragmentAt(layers, ctx, fragmentAngle + attempt * 0.7, rng);
        if (f)
            moveFragment(layers, *f, truth);
    }
}

/// Moves the piece of `f` on every layer and records it in `truth`.
void moveFragment(Layers& layers, const Fragment& fr, GroundTruth& truth) {
    const Fragment* f = &fr;
    const auto move = [&](const cv::Mat& src, int interpolation) {
        cv::Mat part = cv::Mat::zeros(src.size(), src.type()), moved;
        src.copyTo(part, f->piece);
        cv::warpAffine(part, moved, f->motion, src.size(), interpolation, cv::BORDER_CONSTANT,
                       cv::Scalar(0));
        // Replace, not add: the layers hold values outside the tissue too.
        cv::Mat kept = src.clone();
        kept.setTo(0, f->piece | f->moved);
        return cv::Mat(kept + moved);
    };
    layers.coverage = move(layers.coverage, cv::INTER_LINEAR);
    layers.signal = move(layers.signal, cv::INTER_LINEAR);
    layers.nuclei = move(layers.nuclei, cv::INTER_LINEAR);
    layers.level = move(layers.level, cv::INTER_LINEAR);
    if (!layers.labelled.empty())
        layers.labelled = move(layers.labelled, cv::INTER_LINEAR);
    layers.tissue = move(layers.tissue, cv::INTER_NEAREST);
    layers.outline = move(layers.outline, cv::INTER_NEAREST);
    layers.support = move(layers.support, cv::INTER_NEAREST);
    truth.damageMask.setTo(3, f->pieceTissue | (f->moved & layers.outline));
    truth.damage.push_back(DamageRegion{DamageKind::Fragment, outlineOf(f->pieceTissue),
                                        static_cast<double>(cv::countNonZero(f->pieceTissue)),
                                        f->motion});
}

// ---------------------------------------------------------------------------------------------
// The damage models of issue 18 and anatomy that is not damage.

/// Width scale: the models' pixel widths are given at a 1500 px wide image.
double pxScale(const Layers& layers) {
    return layers.tissue.cols / 1500.0;
}

/// A random pixel of `mask` at least `minDistance` px inside it, or nothing.
std::optional<cv::Point> pixelInside(const cv::Mat& mask, double minDistance, Rng& rng) {
    cv::Mat dist;
    cv::distanceTransform(mask, dist, cv::DIST_L2, 3);
    std::vector<cv::Point> candidates;
    cv::findNonZero(dist > minDistance, candidates);
    if (candidates.empty())
        return std::nullopt;
    return candidates[static_cast<size_t>(rng.index(static_cast<int>(candidates.size())))];
}

/// A thin crack crossing the tissue: from a point inside, wandering both ways, 2-5 px wide
/// (at 1500 px) in its middle and tapering to 1 px at both ends.
cv::Mat thinCrackMask(const Layers& layers, const DamageContext& ctx, Rng& rng) {
    cv::Mat m = cv::Mat::zeros(layers.tissue.size(), CV_8U);
    const auto start = pixelInside(layers.tissue, 0.04 * ctx.size, rng);
    if (!start)
        return m;
    const double length = rng.uniform(0.12, 0.3) * ctx.size;
    const double scale = pxScale(layers);
    const double wMid = rng.uniform(2.0, 5.0) * scale, wEnd = std::max(1.0, scale);
    const double heading0 = rng.uniform(0.0, 2.0 * kPi);
    constexpr int kSteps = 30; // per half
    for (int half = 0; half < 2; ++half) {
        double heading = heading0 + half * kPi, turn = 0;
        cv::Point2d p(start->x, start->y);
        for (int i = 0; i < kSteps; ++i) {
            turn = 0.7 * turn + rng.symmetric(0.08);
            heading += turn;
            const cv::Point2d q =
                p + cv::Point2d(std::cos(heading), std::sin(heading)) * (0.5 * length / kSteps);
            const double w = wMid + (wEnd - wMid) * i / (kSteps - 1);
            cv::line(m, cv::Point(cvRound(p.x * 16), cvRound(p.y * 16)),
                     cv::Point(cvRound(q.x * 16), cvRound(q.y * 16)), cv::Scalar(255),
                     std::max(1, static_cast<int>(std::lround(w))), cv::LINE_8, 4);
            p = q;
        }
    }
    return m;
}

/// A wedge of glass out of the largest ventricle: its wall torn open, 1.5-3% of the tissue
/// width wide at the ventricle and 8-15% long, away from the ventricle's centre.
cv::Mat tornVentricleMask(const Layers& layers, const DamageContext& ctx, Rng& rng) {
    cv::Mat m = cv::Mat::zeros(layers.tissue.size(), CV_8U);
    const cv::Mat ventricle = largestComponent(layers.outline & ~layers.tissue);
    const cv::Moments mo = cv::moments(ventricle, true);
    if (mo.m00 < 20)
        return m;
    const cv::Point2d vc(mo.m10 / mo.m00, mo.m01 / mo.m00);
    std::vector<cv::Point> rim;
    cv::Mat grown;
    cv::dilate(ventricle, grown, cv::getStructuringElement(cv::MORPH_ELLIPSE, {3, 3}));
    cv::findNonZero(grown & ~ventricle & layers.tissue, rim);
    if (rim.empty())
        return m;
    const cv::Point r = rim[static_cast<size_t>(rng.index(static_cast<int>(rim.size())))];
    cv::Point2d dir = cv::Point2d(r.x, r.y) - vc;
    const double n = std::hypot(dir.x, dir.y);
    dir = n > 0 ? dir / n : cv::Point2d(1, 0);
    double heading = std::atan2(dir.y, dir.x) + rng.symmetric(0.4);
    const double length = rng.uniform(0.08, 0.15) * ctx.size;
    const double width = rng.uniform(0.015, 0.03) * ctx.size;
    constexpr int kSteps = 24;
    // Start a little inside the ventricle so the wedge opens into it.
    cv::Point2d p = cv::Point2d(r.x, r.y) - cv::Point2d(std::cos(heading), std::sin(heading)) * 3;
    std::vector<cv::Point> left, right;
    double turn = 0;
    for (int i = 0; i <= kSteps; ++i) {
        const double w = 0.5 * width * std::pow(1.0 - double(i) / kSteps, 1.2);
        const cv::Point2d nn(-std::sin(heading), std::cos(heading));
        left.emplace_back(cvRound(p.x + nn.x * w), cvRound(p.y + nn.y * w));
        right.emplace_back(cvRound(p.x - nn.x * w), cvRound(p.y - nn.y * w));
        turn = 0.8 * turn + rng.symmetric(0.05);
        heading += turn;
        p += cv::Point2d(std::cos(heading), std::sin(heading)) * (length / kSteps);
    }
    std::vector<cv::Point> polygon(left);
    polygon.insert(polygon.end(), right.rbegin(), right.rend());
    cv::fillPoly(m, std::vector<std::vector<cv::Point>>{polygon}, cv::Scalar(255));
    return m;
}

/// A flap beyond a chord near the edge folded back over the tissue (reflected about the fold
/// line): the flap's place becomes glass, the band inside the line carries two layers (the
/// flap's stain added with a gain of 0.85-1), and the edge moves to the line.
void paintFold(Layers& layers, const DamageContext& ctx, Rng& rng, GroundTruth& truth) {
    const cv::Point2d n = imageDirection(ctx, rng.uniform(0.0, 2.0 * kPi));
    const cv::Point2d edge = boundaryPoint(layers.outline, ctx.centre, n);
    const double depth = rng.uniform(0.03, 0.06) * ctx.size;
    const double halfLength = rng.uniform(0.08, 0.15) * ctx.size;
    const float gain = static_cast<float>(rng.uniform(0.85, 1.0));
    const cv::Point2d lineP = edge - n * depth, tangent(-n.y, n.x);
    const Layers before{layers.coverage.clone(), layers.signal.clone(),   layers.nuclei.clone(),
                        layers.level.clone(),    layers.labelled.clone(), layers.tissue.clone(),
                        layers.outline.clone(),  layers.support.clone()};
    cv::Mat flapPlace = cv::Mat::zeros(layers.tissue.size(), CV_8U);
    cv::Mat band = flapPlace.clone();
    const int rows = layers.tissue.rows, cols = layers.tissue.cols;
    for (int y = 0; y < rows; ++y)
        for (int x = 0; x < cols; ++x) {
            const cv::Point2d p(x, y);
            const double s = (p - lineP).dot(n);
            if (std::abs((p - lineP).dot(tangent)) > halfLength || s > 2.5 * depth ||
                s < -2.5 * depth)
                continue;
            if (s > 0) {
                if (before.support.at<std::uint8_t>(y, x)) {
                    flapPlace.at<std::uint8_t>(y, x) = 255;
                    layers.coverage.at<float>(y, x) = 0;
                    layers.support.at<std::uint8_t>(y, x) = 0;
                    layers.tissue.at<std::uint8_t>(y, x) = 0;
                    layers.outline.at<std::uint8_t>(y, x) = 0;
                }
                continue;
            }
            const cv::Point2d q = p - n * (2 * s); // the flap pixel now lying on p
            const int qx = cvRound(q.x), qy = cvRound(q.y);
            if (qx < 0 || qy < 0 || qx >= cols || qy >= rows || (q - lineP).dot(n) <= 0 ||
                !before.support.at<std::uint8_t>(qy, qx))
                continue;
            const float cp = before.coverage.at<float>(y, x);
            const float cq = gain * before.coverage.at<float>(qy, qx);
            const float c = cp + cq;
            if (c <= 0)
                continue;
            const auto mix = [&](cv::Mat& dst, const cv::Mat& src) {
                if (!dst.empty())
                    dst.at<float>(y, x) =
                        (cp * src.at<float>(y, x) + cq * src.at<float>(qy, qx)) / c;
            };
            mix(layers.signal, before.signal);
            mix(layers.nuclei, before.nuclei);
            mix(layers.level, before.level);
            mix(layers.labelled, before.labelled);
            layers.coverage.at<float>(y, x) = c;
            layers.support.at<std::uint8_t>(y, x) = 255;
            if (before.tissue.at<std::uint8_t>(qy, qx)) {
                layers.tissue.at<std::uint8_t>(y, x) = 255;
                layers.outline.at<std::uint8_t>(y, x) = 255;
                band.at<std::uint8_t>(y, x) = 255;
            }
        }
    const cv::Mat flapTissue = flapPlace & before.outline;
    if (cv::countNonZero(flapTissue) == 0)
        return;
    truth.damageMask.setTo(4, flapTissue | band);
    truth.damage.push_back(DamageRegion{DamageKind::Fold,
                                        outlineOf(flapTissue | band),
                                        static_cast<double>(cv::countNonZero(flapTissue)),
                                        {1, 0, 0, 0, 1, 0}});
}

/// Knife chatter: across a strip of the section perpendicular to the knife, the thickness
/// (coverage) swings by 30-60% with a period of 1-2.5% of the tissue width.
void paintChatter(Layers& layers, const DamageContext& ctx, Rng& rng, GroundTruth& truth) {
    const cv::Point2d n = imageDirection(ctx, rng.uniform(0.0, 2.0 * kPi)); // across the bands
    const double period = rng.uniform(0.01, 0.025) * ctx.size;
    const double amplitude = rng.uniform(0.3, 0.6);
    const double from = rng.uniform(-0.3, 0.1) * ctx.size,
                 width = rng.uniform(0.15, 0.3) * ctx.size;
    cv::Mat strip = cv::Mat::zeros(layers.tissue.size(), CV_8U);
    for (int y = 0; y < strip.rows; ++y) {
        auto* cov = layers.coverage.ptr<float>(y);
        auto* st = strip.ptr<std::uint8_t>(y);
        for (int x = 0; x < strip.cols; ++x) {
            const double s = (cv::Point2d(x, y) - ctx.centre).dot(n) - from;
            if (s < 0 || s > width)
                continue;
            st[x] = 255;
            cov[x] *= static_cast<float>(1.0 - amplitude * 0.5 *
                                                   (1.0 + std::sin(2.0 * kPi * s / period)));
        }
    }
    const cv::Mat region = strip & layers.tissue;
    if (cv::countNonZero(region) == 0)
        return;
    truth.damageMask.setTo(5, region);
    truth.damage.push_back(DamageRegion{DamageKind::Chatter,
                                        outlineOf(region),
                                        static_cast<double>(cv::countNonZero(region)),
                                        {1, 0, 0, 0, 1, 0}});
}

/// The damage models (DamageOptions::crack and after), painted after the first three kinds.
void paintDamageModels(Layers& layers, const DamageContext& ctx, const GeneratorOptions& o,
                       Rng& rng, GroundTruth& truth) {
    if (o.damage.crack)
        removeTissue(layers, thinCrackMask(layers, ctx, rng), DamageKind::Tear, 1, truth);
    if (o.damage.tornVentricle)
        removeTissue(layers, tornVentricleMask(layers, ctx, rng), DamageKind::Tear, 1, truth);
    if (o.damage.fold)
        paintFold(layers, ctx, rng, truth);
    if (o.damage.smallFragment) {
        std::optional<Fragment> f;
        const double angle = rng.uniform(0.0, 2.0 * kPi);
        for (int attempt = 0; attempt < 8 && !f; ++attempt)
            f = fragmentAt(layers, ctx, angle + attempt * 0.7, rng, 0.01, 0.03);
        if (f)
            moveFragment(layers, *f, truth);
    }
    if (o.damage.chatter)
        paintChatter(layers, ctx, rng, truth);
}

/// Anatomy that is not damage (AnatomyOptions): enlarged ventricles and an opened fissure.
void paintAnatomy(Layers& layers, const DamageContext& ctx, const cv::Mat& labelsInImage,
                  const AnatomyOptions& a, Rng& rng) {
    const auto clear = [&](const cv::Mat& mask, bool outlineToo) {
        layers.coverage.setTo(0.0f, mask);
        layers.support.setTo(0, mask);
        layers.tissue.setTo(0, mask);
        if (outlineToo)
            layers.outline.setTo(0, mask);
    };
    if (a.ventricleGrowthFrac > 0) {
        const cv::Mat ventricles = layers.outline & ~layers.tissue;
        const int r = std::max(1, cvRound(a.ventricleGrowthFrac * ctx.size));
        cv::Mat grown;
        cv::dilate(ventricles, grown,
                   cv::getStructuringElement(cv::MORPH_ELLIPSE, {2 * r + 1, 2 * r + 1}));
        clear(grown & layers.outline, false);
    }
    if (a.fissureOpenFrac <= 0 || a.parts.size() < 2)
        return;
    // The pair of parts touching along the longest interface; open a stretch of it.
    const double half = 0.5 * a.fissureOpenFrac * ctx.size;
    std::vector<cv::Mat> parts, dist;
    for (const auto& ids : a.parts) {
        cv::Mat m = cv::Mat::zeros(labelsInImage.size(), CV_8U);
        for (std::int32_t id : ids)
            m |= labelsInImage == id;
        m &= layers.tissue;
        cv::Mat d;
        cv::distanceTransform(~m, d, cv::DIST_L2, 3);
        parts.push_back(m);
        dist.push_back(d);
    }
    cv::Mat bestInterface;
    int bestLength = 0;
    for (size_t i = 0; i < parts.size(); ++i)
        for (size_t j = i + 1; j < parts.size(); ++j) {
            const cv::Mat interface = parts[i] & (dist[j] <= 2.0f);
            const int length = cv::countNonZero(interface);
            if (length > bestLength) {
                bestLength = length;
                bestInterface =
                    (parts[i] & (dist[j] <= float(half))) | (parts[j] & (dist[i] <= float(half)));
            }
        }
    if (bestLength < 0.05 * ctx.size)
        return;
    const auto centre = pixelInside(bestInterface, 0.0, rng);
    if (!centre)
        return;
    cv::Mat stretch = cv::Mat::zeros(bestInterface.size(), CV_8U);
    cv::circle(stretch, *centre, cvRound(rng.uniform(0.1, 0.25) * ctx.size), cv::Scalar(255), -1);
    clear(bestInterface & stretch, true);
}

// ---------------------------------------------------------------------------------------------
// Landmarks: spread-out pixels of intact tissue, away from every damage.

std::vector<Landmark> pickLandmarks(const TrueMap& map, const cv::Mat& tissueBefore,
                                    const cv::Mat& damageMask, int count, Rng& rng) {
    std::vector<Landmark> out;
    if (count <= 0)
        return out;
    cv::Mat intact = tissueBefore & (damageMask == 0);
    cv::Mat nearDamage;
    cv::dilate(damageMask > 0, nearDamage, cv::getStructuringElement(cv::MORPH_ELLIPSE, {11, 11}));
    intact &= ~nearDamage;
    // A few pixels in from every edge so that a landmark is never on a boundary.
    cv::erode(intact, intact, cv::getStructuringElement(cv::MORPH_ELLIPSE, {7, 7}));
    std::vector<cv::Point> candidates;
    cv::findNonZero(intact, candidates);
    if (candidates.empty())
        return out;
    double spacing = 0.8 * std::sqrt(static_cast<double>(candidates.size()) / count);
    std::vector<cv::Point> chosen;
    for (int round = 0; round < 8 && static_cast<int>(chosen.size()) < count; ++round) {
        // A coarse grid of buckets makes the spacing test local.
        const double cell = std::max(1.0, spacing);
        std::map<std::pair<int, int>, std::vector<cv::Point>> buckets;
        const auto key = [&](cv::Point p) {
            return std::make_pair(static_cast<int>(p.x / cell), static_cast<int>(p.y / cell));
        };
        for (const cv::Point& p : chosen)
            buckets[key(p)].push_back(p);
        const int tries = 40 * count;
        for (int i = 0; i < tries && static_cast<int>(chosen.size()) < count; ++i) {
            const cv::Point p =
                candidates[static_cast<size_t>(rng.index(static_cast<int>(candidates.size())))];
            const auto [kx, ky] = key(p);
            bool free = true;
            for (int dy = -1; dy <= 1 && free; ++dy)
                for (int dx = -1; dx <= 1 && free; ++dx) {
                    const auto it = buckets.find({kx + dx, ky + dy});
                    if (it == buckets.end())
                        continue;
                    for (const cv::Point& q : it->second)
                        if (std::hypot(p.x - q.x, p.y - q.y) < spacing) {
                            free = false;
                            break;
                        }
                }
            if (!free)
                continue;
            chosen.push_back(p);
            buckets[key(p)].push_back(p);
        }
        spacing *= 0.8;
    }
    for (const cv::Point& p : chosen)
        out.push_back({cv::Point2d(p), map(p.x, p.y)});
    return out;
}

// ---------------------------------------------------------------------------------------------
// Slide debris: specks, fibres and a bubble, all clear of the tissue.

struct Debris {
    cv::Mat bright; // CV_32F 0..1: fluorescent dust
    cv::Mat dark;   // CV_32F 0..1: absorbing dirt (brightfield) / faint in fluorescence
};

Debris paintDebris(const cv::Mat& tissue, Rng& rng) {
    cv::Mat away;
    cv::distanceTransform(~tissue, away, cv::DIST_L2, 3);
    cv::Mat layer8 = cv::Mat::zeros(tissue.size(), CV_8U);
    const cv::Size size = tissue.size();
    constexpr double kClearance = 14.0; // more than the blur and the soft edge reach
    const auto clear = [&](cv::Point2d p, double radius) {
        const int x = cvRound(p.x), y = cvRound(p.y);
        if (x < 2 || y < 2 || x >= size.width - 2 || y >= size.height - 2)
            return false;
        return away.at<float>(y, x) > radius + kClearance;
    };
    const auto randomPoint = [&] {
        return cv::Point2d(rng.uniform(0, size.width - 1), rng.uniform(0, size.height - 1));
    };
    const int specks = 3 + rng.index(6);
    for (int i = 0, placed = 0; i < 60 && placed < specks; ++i) {
        const cv::Point2d p = randomPoint();
        const double r = rng.uniform(0.8, 3.5);
        if (!clear(p, r))
            continue;
        cv::circle(layer8, cv::Point(cvRound(p.x * 16), cvRound(p.y * 16)), cvRound(r * 16),
                   cv::Scalar(rng.uniform(120, 255)), cv::FILLED, cv::LINE_AA, 4);
        ++placed;
    }
    const int fibres = 1 + rng.index(3);
    for (int i = 0, placed = 0; i < 60 && placed < fibres; ++i) {
        cv::Point2d p = randomPoint();
        double heading = rng.uniform(0, 2 * kPi), turn = 0;
        const int segments = 8 + rng.index(10);
        std::vector<cv::Point> line;
        bool ok = true;
        for (int s = 0; s <= segments && ok; ++s) {
            ok = clear(p, 1.0);
            line.emplace_back(cvRound(p.x * 16), cvRound(p.y * 16));
            turn = 0.7 * turn + rng.symmetric(0.25);
            heading += turn;
            p += cv::Point2d(std::cos(heading), std::sin(heading)) * 7.0;
        }
        if (!ok)
            continue;
        cv::polylines(layer8, line, false, cv::Scalar(rng.uniform(90, 200)), 1, cv::LINE_AA, 4);
        ++placed;
    }
    if (rng.chance(0.7)) {
        for (int i = 0; i < 40; ++i) {
            const cv::Point2d p = randomPoint();
            const double r = rng.uniform(12.0, 45.0);
            if (!clear(p, r + 2))
                continue;
            cv::circle(layer8, cv::Point(cvRound(p.x * 16), cvRound(p.y * 16)), cvRound(r * 16),
                       cv::Scalar(110), 2, cv::LINE_AA, 4);
            break;
        }
    }
    Debris d;
    layer8.convertTo(d.bright, CV_32F, 1.0 / 255.0);
    d.dark = d.bright;
    return d;
}

// ---------------------------------------------------------------------------------------------
// Imaging: illumination, optics, sensor.

cv::Mat illumination(cv::Size size, Rng& rng) {
    const double vignette = rng.uniform(0.08, 0.22);
    const double gx = rng.symmetric(0.08), gy = rng.symmetric(0.08);
    const double cx = 0.5 * (size.width - 1) + rng.symmetric(0.1) * size.width;
    const double cy = 0.5 * (size.height - 1) + rng.symmetric(0.1) * size.height;
    const double r2max =
        0.25 * (double(size.width) * size.width + double(size.height) * size.height);
    cv::Mat out(size, CV_32F);
    for (int r = 0; r < size.height; ++r) {
        auto* p = out.ptr<float>(r);
        const double dy = r - cy;
        for (int c = 0; c < size.width; ++c) {
            const double dx = c - cx;
            p[c] = static_cast<float>((1.0 - vignette * (dx * dx + dy * dy) / r2max) *
                                      (1.0 + gx * (c / double(size.width) - 0.5) * 2.0 +
                                       gy * (r / double(size.height) - 0.5) * 2.0));
        }
    }
    return out;
}

cv::Mat renderFluorescence(const Layers& layers, const Debris& debris, const cv::Mat& light,
                           double noise, std::uint64_t noiseSeed, Rng& rng) {
    const float glass = static_cast<float>(rng.uniform(0.01, 0.03));
    cv::Mat signal = glass + layers.coverage.mul(layers.signal) + 0.5f * debris.bright;
    signal = signal.mul(light);
    cv::GaussianBlur(signal, signal, cv::Size(), rng.uniform(1.0, 1.5));
    // Expose so the brightest tissue lands at ~80% of the range, below saturation even after
    // noise; a sensor black level keeps the glass off zero.
    double maxSignal = 0;
    cv::minMaxLoc(signal, nullptr, &maxSignal);
    constexpr double kElectronsAtMax = 3000.0, kReadNoiseE = 6.0, kBlackLevelDn = 300.0;
    const double dnPerElectron = 0.8 * (65535.0 - kBlackLevelDn) / kElectronsAtMax;
    const double electronsPerUnit = kElectronsAtMax / std::max(1e-6, maxSignal);
    // Shot and read noise are independent Gaussians (shot noise approximates Poisson at these
    // counts), so one normal draw with the summed variance is the same distribution.
    const cv::Mat normal = normalField(signal.size(), noiseSeed);
    cv::Mat out(signal.size(), CV_16U);
    cv::parallel_for_(cv::Range(0, signal.rows), [&](const cv::Range& rows) {
        for (int r = rows.start; r < rows.end; ++r) {
            const auto* s = signal.ptr<float>(r);
            const auto* n = normal.ptr<float>(r);
            auto* o = out.ptr<std::uint16_t>(r);
            for (int c = 0; c < signal.cols; ++c) {
                const double e = std::max(0.0, s[c] * electronsPerUnit);
                const double noisy = e + noise * std::sqrt(e + kReadNoiseE * kReadNoiseE) * n[c];
                o[c] = cv::saturate_cast<std::uint16_t>(kBlackLevelDn + noisy * dnPerElectron);
            }
        }
    });
    return out;
}

cv::Mat renderBrightfield(const Layers& layers, const Debris& debris, const cv::Mat& light,
                          double noise, std::uint64_t noiseSeed, Rng& rng) {
    // Beer-Lambert with two stains: a basic dye on nuclei (purple-blue) and a pink counterstain
    // proportional to the region's level. Optical densities per unit stain, in R, G, B.
    const cv::Vec3f nuclear(0.65f, 0.75f, 0.30f), counter(0.08f, 0.85f, 0.18f);
    const float lamp = static_cast<float>(rng.uniform(0.88, 0.95));
    std::array<cv::Mat, 3> rgb;
    for (int ch = 0; ch < 3; ++ch) {
        cv::Mat od = layers.coverage.mul(nuclear[ch] * (0.06f + 0.75f * layers.nuclei) +
                                         counter[ch] * (0.1f + 0.55f * layers.level));
        od += (0.5f * nuclear[ch] + 0.2f) * debris.dark;
        if (!layers.labelled.empty()) // DAB-like brown: absorbs blue most (R, G, B)
            od +=
                layers.coverage.mul(layers.labelled) * std::array{0.27f, 0.57f, 0.78f}[size_t(ch)];
        cv::exp(-od, rgb[static_cast<size_t>(ch)]);
        rgb[static_cast<size_t>(ch)] = rgb[static_cast<size_t>(ch)].mul(light) * lamp;
    }
    const double sigma = rng.uniform(1.0, 1.5);
    cv::Mat out(layers.coverage.size(), CV_8UC3);
    std::array<cv::Mat, 3> noiseFields;
    for (int ch = 0; ch < 3; ++ch) {
        cv::GaussianBlur(rgb[static_cast<size_t>(ch)], rgb[static_cast<size_t>(ch)], cv::Size(),
                         sigma);
        noiseFields[static_cast<size_t>(ch)] =
            normalField(out.size(), noiseSeed + static_cast<std::uint64_t>(ch) * 7919);
    }
    cv::parallel_for_(cv::Range(0, out.rows), [&](const cv::Range& rows) {
        for (int r = rows.start; r < rows.end; ++r) {
            auto* o = out.ptr<cv::Vec3b>(r);
            for (int c = 0; c < out.cols; ++c)
                for (int ch = 0; ch < 3; ++ch) {
                    const double v = 255.0 * rgb[static_cast<size_t>(ch)].ptr<float>(r)[c];
                    const double n = noise * (1.2 + 0.08 * std::sqrt(std::max(0.0, v))) *
                                     noiseFields[static_cast<size_t>(ch)].ptr<float>(r)[c];
                    o[c][2 - ch] = cv::saturate_cast<std::uint8_t>(v + n); // BGR
                }
        }
    });
    return out;
}

core::Result<GeneratedSection> generate(const cv::Mat& labels, const GeneratorOptions& o) {
    Rng rng(o.seed);
    // Separate streams for the independent parts, so e.g. turning damage on does not change
    // the geometry of the same seed.
    Rng geometryRng(rng.bits()), lookRng(rng.bits()), damageRng(rng.bits()), debrisRng(rng.bits()),
        imagingRng(rng.bits()), landmarkRng(rng.bits());
    const std::uint64_t cellSeed = rng.bits(), noiseSeed = rng.bits();
    // Drawn after the others, so that cases without the issue-18 models keep their bytes.
    Rng modelsRng(rng.bits()), anatomyRng(rng.bits());

    const AtlasTissue tissue = describeTissue(labels);
    const Placement placement = placeSection(tissue, o, geometryRng);
    GeneratedSection out;
    GroundTruth& truth = out.truth;
    truth.affineAtlasFromImage = placement.map.atlasFromImage;
    evaluateMap(placement.map, o.imageSize, truth.atlasX, truth.atlasY);
    truth.labelsInImage = seeThroughMap(labels, truth.atlasX, truth.atlasY, cv::INTER_NEAREST, 0);

    const auto looks = makeLooks(labels, o, lookRng);
    const AtlasMaps atlasMaps = renderAtlasMaps(labels, looks, tissue);
    Layers layers;
    layers.coverage =
        seeThroughMap(atlasMaps.coverage, truth.atlasX, truth.atlasY, cv::INTER_LINEAR, 0);
    const cv::Mat regionLevel =
        seeThroughMap(atlasMaps.level, truth.atlasX, truth.atlasY, cv::INTER_LINEAR, 0);
    const cv::Mat density =
        seeThroughMap(atlasMaps.density, truth.atlasX, truth.atlasY, cv::INTER_LINEAR, 0);
    layers.outline = truth.labelsInImage > 0;
    layers.support = layers.coverage > 0.01f;
    layers.tissue = layers.outline.clone();
    for (const auto& [id, look] : looks)
        if (look.empty)
            layers.tissue.setTo(0, truth.labelsInImage == id);
    const DamageContext ctx{[&] {
                                const cv::Moments m = cv::moments(layers.outline, true);
                                return cv::Point2d(m.m10 / m.m00, m.m01 / m.m00);
                            }(),
                            placement.tissueWidthPx, placement.linear};
    // Not damage: the section's own anatomy, so landmarks avoid it like any glass.
    paintAnatomy(layers, ctx, truth.labelsInImage, o.anatomy, anatomyRng);
    const cv::Mat tissueBefore = layers.tissue.clone();

    // Cell texture: nuclei as blurred impulses whose density follows the region, plus a fine
    // neuropil speckle and slow variations of the staining.
    const cv::Size size = o.imageSize;
    cv::Mat cells(size, CV_32F), speckle(size, CV_32F);
    cv::parallel_for_(cv::Range(0, size.height), [&](const cv::Range& rows) {
        for (int r = rows.start; r < rows.end; ++r) {
            RowRng cellRng(cellSeed, r);
            const auto* d = density.ptr<float>(r);
            auto* p = cells.ptr<float>(r);
            auto* sp = speckle.ptr<float>(r);
            for (int c = 0; c < size.width; ++c) {
                const float u = cellRng.uniform(), brightness = cellRng.uniform();
                p[c] = u < 0.05f * d[c] ? 0.6f + 0.8f * brightness : 0.0f;
                sp[c] = 3.46f * (cellRng.uniform() - 0.5f); // unit variance
            }
        }
    });
    constexpr double kNucleusSigma = 1.1;
    cv::GaussianBlur(cells, cells, cv::Size(), kNucleusSigma);
    cells *= 2.0 * kPi * kNucleusSigma * kNucleusSigma; // unit peak per nucleus
    cv::GaussianBlur(speckle, speckle, cv::Size(), 0.7);
    const cv::Mat slow = smoothField(size, 6, lookRng);
    cv::Mat rimDistance;
    cv::distanceTransform(layers.outline, rimDistance, cv::DIST_L2, 3);
    cv::Mat rim;
    cv::exp(rimDistance * (-1.0 / 3.0), rim);
    // Nuclei dominate a DAPI-like image; the level sets the region's overall brightness.
    layers.level = regionLevel.mul(1.0f + 0.12f * slow);
    layers.nuclei = cells;
    layers.signal = layers.level.mul(0.35f + 0.8f * cells + 0.1f * speckle).mul(1.0f + 0.35f * rim);
    if (o.cells.enabled) {
        // Labelled cells (issue 22) on their own random stream: fluorescence adds their stain to
        // the signal, brightfield their absorbing dye to the nuclear layer (dark cells).
        out.cells = placeCells(truth.labelsInImage, layers.tissue, o.cells, o.seed);
        const cv::Mat blobs = renderCells(size, out.cells, o.cells.diameterPx);
        double maxLevel = 0;
        cv::minMaxLoc(regionLevel, nullptr, &maxLevel);
        if (o.stain == Stain::Fluorescence)
            layers.signal += blobs * (o.cells.contrast * maxLevel);
        else
            layers.labelled = blobs * o.cells.contrast;
    }

    truth.damageMask = cv::Mat::zeros(layers.tissue.size(), CV_8U);
    paintDamage(layers, ctx, o, damageRng, truth);
    paintDamageModels(layers, ctx, o, modelsRng, truth);
    truth.tissueMask = layers.tissue;
    markCounted(out.cells, truth.tissueMask, truth.damageMask);
    truth.landmarks =
        pickLandmarks(placement.map, tissueBefore, truth.damageMask, o.landmarkCount, landmarkRng);

    const Debris debris = paintDebris(layers.outline | layers.tissue, debrisRng);
    const cv::Mat light = illumination(size, imagingRng);
    if (o.stain == Stain::Fluorescence)
        out.image = renderFluorescence(layers, debris, light, o.noise, noiseSeed, imagingRng);
    else
        out.image = renderBrightfield(layers, debris, light, o.noise, noiseSeed, imagingRng);
    return out;
}

} // namespace

core::Result<GeneratedSection> generateSection(const cv::Mat& atlasLabels,
                                               const GeneratorOptions& options) {
    if (auto error = validate(atlasLabels, options))
        return *error;
    try {
        return generate(atlasLabels, options);
    } catch (const cv::Exception& e) {
        return makeError(ErrorCode::Internal,
                         std::string("section generator: OpenCV: ") + e.what());
    } catch (const std::bad_alloc&) {
        return makeError(ErrorCode::Internal, "section generator: out of memory");
    }
}

std::string_view toString(DamageKind kind) noexcept {
    switch (kind) {
    case DamageKind::Tear:
        return "tear";
    case DamageKind::Missing:
        return "missing";
    case DamageKind::Fragment:
        return "fragment";
    case DamageKind::Fold:
        return "fold";
    case DamageKind::Chatter:
        return "chatter";
    }
    return "?";
}

} // namespace slicestation::sim
