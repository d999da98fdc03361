#include "slicestation/sim/builtin_atlas.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>

namespace slicestation::sim {

namespace {

// Allen CCFv3 ids of the imitated structures.
constexpr std::int32_t kIsocortex = 315;
constexpr std::int32_t kCorticalSubplate = 703;
constexpr std::int32_t kOlfactoryAreas = 698;
constexpr std::int32_t kHippocampalRegion = 1080;
constexpr std::int32_t kCaudoputamen = 672;
constexpr std::int32_t kPallidum = 803;
constexpr std::int32_t kThalamus = 549;
constexpr std::int32_t kHypothalamus = 1097;
constexpr std::int32_t kMidbrain = 313;

// Shape coordinates: x >= 0 is the distance from the midline and y points ventrally, both in
// units of the hemisphere half-width at mid levels; the brain spans about y in [-0.71, 0.71].
constexpr double kHalfWidthOfImage = 0.425; // half-width of the shape / image width
constexpr double kHalfHeightUnits = 0.72;   // a little above the tallest level's half-height

double smoothstep(double e0, double e1, double t) {
    const double u = std::clamp((t - e0) / (e1 - e0), 0.0, 1.0);
    return u * u * (3.0 - 2.0 * u);
}

/// 1 inside [lo, hi], easing to 0 over `ramp` on both sides.
double window(double a, double lo, double hi, double ramp) {
    return smoothstep(lo - ramp, lo, a) * (1.0 - smoothstep(hi, hi + ramp, a));
}

double gauss(double t, double centre, double width) {
    const double d = (t - centre) / width;
    return std::exp(-d * d);
}

/// Squared normalised radius of (x, y) in an ellipse rotated by `angleRad`; < 1 is inside.
double ellipse(double x, double y, double cx, double cy, double rx, double ry,
               double angleRad = 0.0) {
    const double c = std::cos(angleRad), s = std::sin(angleRad);
    const double dx = x - cx, dy = y - cy;
    const double u = (c * dx + s * dy) / rx, v = (-s * dx + c * dy) / ry;
    return u * u + v * v;
}

/// A structure of the subcortical mass; the mass is split between the present structures by
/// their normalised elliptic distance, so the boundaries are conics and change smoothly with AP.
struct Nucleus {
    std::int32_t id;
    double cx, cy, rx, ry, presence;
};

/// Everything that depends on the AP level only, computed once per plane.
struct Level {
    double widthFactor, heightFactor, hypothalamicBulge;
    double rhinalY;            // cortex above, olfactory (piriform) areas below
    double hippocampus;        // presence 0..1
    double lateralVentricle;   // presence 0..1
    double thirdVentricle;     // presence 0..1
    double internalCapsule;    // presence 0..1
    double anteriorCommissure; // presence 0..1
    double amygdala;           // presence 0..1 (basolateral part of the cortical subplate)
    std::array<Nucleus, 7> nuclei;
};

Level makeLevel(double a) {
    Level l{};
    // The front and the back of the forebrain are narrower than its middle.
    l.widthFactor = 1.0 - 0.12 * (1.0 - smoothstep(0.0, 0.45, a)) - 0.05 * smoothstep(0.75, 1.0, a);
    l.heightFactor = 1.0 - 0.06 * (1.0 - smoothstep(0.0, 0.4, a));
    l.hypothalamicBulge = window(a, 0.25, 0.75, 0.15);
    l.rhinalY = 0.30 - 0.12 * (1.0 - smoothstep(0.0, 0.35, a)) + 0.05 * smoothstep(0.6, 1.0, a);
    l.hippocampus = smoothstep(0.28, 0.5, a);
    l.lateralVentricle = 1.0 - smoothstep(0.45, 0.7, a);
    l.thirdVentricle = window(a, 0.35, 0.75, 0.08);
    l.internalCapsule = window(a, 0.3, 0.75, 0.12);
    l.anteriorCommissure = 1.0 - smoothstep(0.15, 0.3, a);
    l.amygdala = window(a, 0.45, 0.8, 0.12);
    // The striatum shrinks towards the external capsule as the thalamus takes over.
    const double striatum = 1.0 - smoothstep(0.35, 0.7, a);
    l.nuclei = {{
        {kCaudoputamen, 0.45 + 0.25 * (1.0 - striatum), 0.02, 0.30, 0.34, striatum},
        {kPallidum, 0.30, 0.36, 0.17, 0.14, window(a, 0.2, 0.55, 0.12)},
        {kOlfactoryAreas, 0.20, 0.60, 0.24, 0.13, 1.0 - smoothstep(0.05, 0.35, a)},
        {kThalamus, 0.0, 0.10, 0.38, 0.28, window(a, 0.35, 0.75, 0.15)},
        {kHypothalamus, 0.0, 0.52, 0.22, 0.20, window(a, 0.2, 0.8, 0.15)},
        {kMidbrain, 0.0, 0.22, 0.46, 0.52, smoothstep(0.45, 0.85, a)},
        {kOlfactoryAreas, 0.74, 0.52, 0.20, 0.15, 1.0}, // piriform/cortical amygdala
    }};
    return l;
}

std::int32_t subcorticalLabel(double x, double y, const Level& l) {
    if (l.lateralVentricle > 0.05 && ellipse(x, y, 0.17, -0.13, 0.024 * l.lateralVentricle,
                                             0.14 * l.lateralVentricle, -0.35) < 1.0)
        return kVentricularSystemsId;
    if (l.thirdVentricle > 0.05 && ellipse(x, y, 0.0, 0.36, 0.013, 0.13 * l.thirdVentricle) < 1.0)
        return kVentricularSystemsId;
    if (l.internalCapsule > 0.05 &&
        ellipse(x, y, 0.46, 0.30, 0.035, 0.19 * l.internalCapsule, 0.6) < 1.0)
        return kFiberTractsId;
    if (l.anteriorCommissure > 0.05 &&
        ellipse(x, y, 0.17, 0.40, 0.05 * l.anteriorCommissure, 0.035 * l.anteriorCommissure) < 1.0)
        return kFiberTractsId;
    if (l.hippocampus > 0.05 && x > 0.035) {
        // A crescent under the corpus callosum, opening ventrally, growing from its dorsal edge.
        const double p = l.hippocampus;
        const double outer = ellipse(x, y, 0.33, -0.40 + 0.30 * p, 0.34 * p, 0.30 * p);
        const double inner = ellipse(x, y, 0.36, -0.40 + 0.12 * p + 0.30 * p, 0.30 * p, 0.30 * p);
        if (outer < 1.0 && inner >= 1.0)
            return kHippocampalRegion;
    }
    if (l.amygdala > 0.05 && ellipse(x, y, 0.70, 0.42, 0.12 * l.amygdala, 0.10 * l.amygdala) < 1.0)
        return kCorticalSubplate;
    std::int32_t best = kCaudoputamen;
    double bestD = std::numeric_limits<double>::infinity();
    for (const Nucleus& n : l.nuclei) {
        if (n.presence < 0.02)
            continue;
        const double d = ellipse(x, y, n.cx, n.cy, n.rx * n.presence, n.ry * n.presence);
        if (d < bestD) {
            bestD = d;
            best = n.id;
        }
    }
    return best;
}

/// The label at shape coordinates (x >= 0, y) of the level `l`.
std::int32_t labelAt(double x, double y, const Level& l) {
    const double xs = x / l.widthFactor;
    if (xs >= 1.0)
        return 0;
    constexpr double kCentreY = 0.06; // the lateral tips sit a little below the middle
    const double h = l.heightFactor;
    const double notch = 0.05 * gauss(x, 0.0, 0.04);
    const double top = kCentreY - h * 0.77 * std::sqrt(1.0 - std::pow(xs, 2.4)) + notch;
    const double bottom =
        kCentreY + h * std::sqrt(1.0 - xs * xs) * (0.50 + 0.20 * gauss(xs, 0.66, 0.17)) +
        0.13 * l.hypothalamicBulge * gauss(xs, 0.0, 0.17) - 0.03 * gauss(xs, 0.33, 0.07);
    if (y < top || y > bottom)
        return 0;

    // Corpus callosum / external capsule: an elliptic band, thicker near the midline.
    const double rxCc = 0.80 * l.widthFactor, ryCc = 0.74 * h, cyCc = 0.22;
    const double rho = std::sqrt(ellipse(x, y, 0.0, cyCc, rxCc, ryCc));
    const double thickness = 0.045 + 0.035 * gauss(x, 0.0, 0.3);
    const double ccTopAtMidline = cyCc - ryCc;
    // The interhemispheric fissure runs from the notch down to the corpus callosum.
    const double fissureHalfWidth = 0.003 + 0.006 * smoothstep(ccTopAtMidline, top, y);
    if (x < fissureHalfWidth && y < ccTopAtMidline)
        return 0;

    if (rho > 1.0) {
        if (ellipse(x, y, 0.85, 0.25, 0.05, 0.15, 0.35) < 1.0)
            return kCorticalSubplate;
        return y < l.rhinalY + 0.04 * (1.0 - xs) ? kIsocortex : kOlfactoryAreas;
    }
    constexpr double kExternalCapsuleEndY = 0.32;
    if (rho > 1.0 - thickness && y < kExternalCapsuleEndY)
        return kFiberTractsId;
    return subcorticalLabel(x, y, l);
}

} // namespace

const std::vector<RegionInfo>& builtinRegions() {
    static const std::vector<RegionInfo> kRegions = {
        {kIsocortex, "Isocortex", "Isocortex", 0x70FF71},
        {kCorticalSubplate, "Cortical subplate", "CTXsp", 0x8ADA87},
        {kOlfactoryAreas, "Olfactory areas", "OLF", 0x9AD2BD},
        {kHippocampalRegion, "Hippocampal region", "HIP", 0x7ED04B},
        {kCaudoputamen, "Caudoputamen", "CP", 0x98D6F9},
        {kPallidum, "Pallidum", "PAL", 0x8599CC},
        {kThalamus, "Thalamus", "TH", 0xFF7080},
        {kHypothalamus, "Hypothalamus", "HY", 0xE64438},
        {kMidbrain, "Midbrain", "MB", 0xFF64FF},
        {kFiberTractsId, "fiber tracts", "fiber tracts", 0xCCCCCC},
        {kVentricularSystemsId, "ventricular systems", "VS", 0xAAAAAA},
    };
    return kRegions;
}

cv::Mat builtinAtlasPlane(double apFraction, cv::Size size) {
    if (size.width < 1 || size.height < 1)
        return {};
    const double a = std::isfinite(apFraction) ? std::clamp(apFraction, 0.0, 1.0) : 0.5;
    const Level level = makeLevel(a);
    // Pixels per shape unit: the shape's width is a fixed fraction of the image width unless
    // the image is too flat for it.
    const double scale =
        std::min(kHalfWidthOfImage * size.width, 0.46 * size.height / kHalfHeightUnits);
    const double cx = 0.5 * (size.width - 1), cy = 0.5 * (size.height - 1);
    cv::Mat labels(size, CV_32S, cv::Scalar(0));
    const int half = (size.width + 1) / 2; // left half including an odd width's centre column
    for (int r = 0; r < size.height; ++r) {
        auto* row = labels.ptr<std::int32_t>(r);
        const double y = (r - cy) / scale;
        for (int c = 0; c < half; ++c) {
            const std::int32_t label = labelAt((cx - c) / scale, y, level);
            // Filling both halves from one evaluation makes the symmetry exact by construction.
            row[c] = label;
            row[size.width - 1 - c] = label;
        }
    }
    return labels;
}

} // namespace slicestation::sim
