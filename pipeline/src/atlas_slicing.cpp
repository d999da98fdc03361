#include "slicestation/pipeline/atlas_slicing.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <sstream>
#include <string>

namespace slicestation::pipeline {
namespace {

using core::ErrorCode;
using core::makeError;

constexpr double kPi = 3.14159265358979323846;
constexpr double kMaxTiltDeg = 60;

/// How atlas-frame voxel indices (AP, DV, LR) reach the volume's storage: sizes and spacings per
/// atlas axis, and linear strides (negative for the axes QuickNII stores reversed).
struct AxisMap {
    std::array<int, 3> size{};
    std::array<double, 3> spacingUm{};
    std::array<std::int64_t, 3> stride{};
    std::int64_t base = 0;
};

AxisMap axisMap(const core::Volume& v, VolumeAxes axes) {
    const auto& s = v.sizes;
    const std::int64_t s0 = s[0], s01 = std::int64_t(s[0]) * s[1];
    AxisMap m;
    if (axes == VolumeAxes::Allen) {
        m.size = {s[0], s[1], s[2]};
        m.spacingUm = {v.spacingUm[0], v.spacingUm[1], v.spacingUm[2]};
        m.stride = {1, s0, s01};
    } else {
        // QuickNII (README): x = LR, y = posterior->anterior (y = last - AP),
        // z = inferior->superior (z = last - DV).
        m.size = {s[1], s[2], s[0]};
        m.spacingUm = {v.spacingUm[1], v.spacingUm[2], v.spacingUm[0]};
        m.stride = {-s0, -s01, 1};
        m.base = std::int64_t(s[1] - 1) * s0 + std::int64_t(s[2] - 1) * s01;
    }
    return m;
}

/// Untilted normal, column and row directions (atlas frame), and the axis index of each.
struct Layout {
    int normalAxis, columnAxis, rowAxis;
};

Layout layout(PlaneOrientation o) {
    switch (o) {
    case PlaneOrientation::Sagittal:
        return {2, 0, 1};
    case PlaneOrientation::Horizontal:
        return {1, 2, 0};
    case PlaneOrientation::Coronal:
        break;
    }
    return {0, 2, 1};
}

cv::Vec3d unit(int axis) {
    cv::Vec3d v(0, 0, 0);
    v[axis] = 1;
    return v;
}

} // namespace

std::string_view toString(PlaneOrientation o) noexcept {
    switch (o) {
    case PlaneOrientation::Sagittal:
        return "sagittal";
    case PlaneOrientation::Horizontal:
        return "horizontal";
    case PlaneOrientation::Coronal:
        break;
    }
    return "coronal";
}

core::Result<PlaneOrientation> parsePlaneOrientation(std::string_view name) {
    if (name == "coronal")
        return PlaneOrientation::Coronal;
    if (name == "sagittal")
        return PlaneOrientation::Sagittal;
    if (name == "horizontal")
        return PlaneOrientation::Horizontal;
    return makeError(ErrorCode::InvalidArgument,
                     "plane '" + std::string(name) + "' is not coronal, sagittal or horizontal");
}

cv::Vec3d volumeExtentUm(const core::Volume& volume, VolumeAxes axes) {
    const AxisMap m = axisMap(volume, axes);
    return {(m.size[0] - 1) * m.spacingUm[0], (m.size[1] - 1) * m.spacingUm[1],
            (m.size[2] - 1) * m.spacingUm[2]};
}

core::Result<SliceGeometry> planeGeometry(const core::Volume& volume, VolumeAxes axes,
                                          const CuttingPlane& plane) {
    if (!(plane.umPerPx > 0) || !std::isfinite(plane.umPerPx))
        return makeError(ErrorCode::InvalidArgument, "um_per_px must be a positive number");
    if (!std::isfinite(plane.positionUm) || !std::isfinite(plane.tiltColumnsDeg) ||
        !std::isfinite(plane.tiltRowsDeg))
        return makeError(ErrorCode::InvalidArgument, "plane position and tilts must be finite");
    if (std::abs(plane.tiltColumnsDeg) > kMaxTiltDeg || std::abs(plane.tiltRowsDeg) > kMaxTiltDeg)
        return makeError(ErrorCode::InvalidArgument,
                         "tilt beyond " + std::to_string(int(kMaxTiltDeg)) +
                             " degrees: that is another orientation, not a tilt");
    const AxisMap m = axisMap(volume, axes);
    for (int a = 0; a < 3; ++a)
        if (!(m.spacingUm[a] > 0) || m.size[a] < 1)
            return makeError(ErrorCode::InvalidArgument,
                             "volume has no voxel size along axis " + std::to_string(a) +
                                 " (NRRD 'space directions' or 'spacings' missing)");
    const Layout l = layout(plane.orientation);
    const double lastUm = (m.size[l.normalAxis] - 1) * m.spacingUm[l.normalAxis];
    // Half a voxel of slack: the outermost voxels own the space up to their faces.
    const double slack = 0.5 * m.spacingUm[l.normalAxis];
    if (plane.positionUm < -slack || plane.positionUm > lastUm + slack)
        return makeError(ErrorCode::OutOfRange,
                         std::string(toString(plane.orientation)) + " plane at " +
                             std::to_string(plane.positionUm) + " um is outside the volume (0.." +
                             std::to_string(lastUm) + " um along its normal)");

    // Tilts as two rotations: first the normal leans toward the column axis, then toward the
    // row axis; the in-plane axes follow so the frame stays orthonormal.
    const double a = plane.tiltColumnsDeg * kPi / 180, b = plane.tiltRowsDeg * kPi / 180;
    const cv::Vec3d n0 = unit(l.normalAxis), u0 = unit(l.columnAxis), v0 = unit(l.rowAxis);
    const cv::Vec3d n1 = std::cos(a) * n0 + std::sin(a) * u0;
    const cv::Vec3d u = -std::sin(a) * n0 + std::cos(a) * u0;
    const cv::Vec3d n = std::cos(b) * n1 + std::sin(b) * v0;
    const cv::Vec3d v = -std::sin(b) * n1 + std::cos(b) * v0;

    const double extentU = m.size[l.columnAxis] * m.spacingUm[l.columnAxis];
    const double extentV = m.size[l.rowAxis] * m.spacingUm[l.rowAxis];
    // In doubles until bounded: a tiny pixel size would overflow int.
    const double widthPx = std::max(1.0, std::round(extentU / std::cos(a) / plane.umPerPx));
    const double heightPx = std::max(1.0, std::round(extentV / std::cos(b) / plane.umPerPx));
    if (!(widthPx * heightPx <= double(kMaxSlicePixels))) {
        std::ostringstream os;
        os << "a plane at " << plane.umPerPx << " um/px is " << widthPx << " x " << heightPx
           << " px, more than " << kMaxSlicePixels << " px (raise the pixel size)";
        return makeError(ErrorCode::InvalidArgument, os.str());
    }
    SliceGeometry g;
    g.size = cv::Size(int(widthPx), int(heightPx));
    cv::Vec3d centre;
    for (int i = 0; i < 3; ++i)
        centre[i] = 0.5 * (m.size[i] - 1) * m.spacingUm[i];
    centre[l.normalAxis] = plane.positionUm;
    g.columnUm = plane.umPerPx * u;
    g.rowUm = plane.umPerPx * v;
    g.normal = n;
    g.originUm =
        centre - 0.5 * (g.size.width - 1) * g.columnUm - 0.5 * (g.size.height - 1) * g.rowUm;
    g.positionUm = plane.positionUm;
    return g;
}

core::Result<cv::Mat> sampleLabels(const core::Volume& volume, VolumeAxes axes,
                                   const SliceGeometry& g) {
    const AxisMap m = axisMap(volume, axes);
    CV_Assert(volume.data.size() == size_t(m.size[0]) * m.size[1] * m.size[2]);
    cv::Mat out(g.size, CV_32S, cv::Scalar(0));
    // Work in voxel units so each pixel costs three multiply-adds and three roundings.
    cv::Vec3d o, du, dv;
    for (int i = 0; i < 3; ++i) {
        o[i] = g.originUm[i] / m.spacingUm[i];
        du[i] = g.columnUm[i] / m.spacingUm[i];
        dv[i] = g.rowUm[i] / m.spacingUm[i];
    }
    const std::uint32_t* data = volume.data.data();
    std::uint32_t maxSeen = 0;
    for (int r = 0; r < g.size.height; ++r) {
        int* row = out.ptr<int>(r);
        const cv::Vec3d start = o + double(r) * dv;
        for (int c = 0; c < g.size.width; ++c) {
            std::int64_t offset = m.base;
            bool inside = true;
            for (int i = 0; i < 3 && inside; ++i) {
                const double x = start[i] + c * du[i];
                // floor(x + 0.5): the voxel whose cell holds the point (ties go up, as lround
                // does for positive values, without its cost).
                const int k = int(std::floor(x + 0.5));
                inside = k >= 0 && k < m.size[i];
                offset += std::int64_t(k) * m.stride[i];
            }
            if (!inside)
                continue;
            const std::uint32_t id = data[offset];
            maxSeen = std::max(maxSeen, id);
            row[c] = static_cast<int>(id);
        }
    }
    if (maxSeen > std::uint32_t(std::numeric_limits<int>::max()))
        return makeError(ErrorCode::InvalidArgument,
                         "label id " + std::to_string(maxSeen) + " does not fit 31 bits");
    return out;
}

core::Result<cv::Vec3d> intensityFrameOffsetUm(const core::Volume& labels, VolumeAxes labelAxes,
                                               const core::Volume& intensity,
                                               VolumeAxes intensityAxes) {
    const AxisMap l = axisMap(labels, labelAxes), t = axisMap(intensity, intensityAxes);
    cv::Vec3d offset;
    for (int i = 0; i < 3; ++i) {
        if (!(l.spacingUm[i] > 0) || !(t.spacingUm[i] > 0))
            return makeError(ErrorCode::InvalidArgument,
                             "a volume has no voxel size along atlas axis " + std::to_string(i));
        const double el = l.size[i] * l.spacingUm[i], et = t.size[i] * t.spacingUm[i];
        if (std::abs(el - et) > t.spacingUm[i]) {
            std::ostringstream os;
            os << "the intensity volume spans " << et << " um along atlas axis " << i
               << ", the labels " << el << " um: not the same space";
            return makeError(ErrorCode::InvalidArgument, os.str());
        }
        offset[i] = 0.5 * (l.spacingUm[i] - t.spacingUm[i]);
    }
    return offset;
}

cv::Mat sampleIntensity(const core::Volume& volume, VolumeAxes axes, const SliceGeometry& g,
                        const cv::Vec3d& offsetUm, double scale) {
    CV_Assert(scale > 0);
    const AxisMap m = axisMap(volume, axes);
    CV_Assert(volume.data.size() == size_t(m.size[0]) * m.size[1] * m.size[2]);
    cv::Mat out(g.size, CV_32F, cv::Scalar(0));
    cv::Vec3d o, du, dv;
    for (int i = 0; i < 3; ++i) {
        o[i] = (g.originUm[i] + offsetUm[i]) / m.spacingUm[i];
        du[i] = g.columnUm[i] / m.spacingUm[i];
        dv[i] = g.rowUm[i] / m.spacingUm[i];
    }
    const std::uint32_t* data = volume.data.data();
    for (int r = 0; r < g.size.height; ++r) {
        float* row = out.ptr<float>(r);
        const cv::Vec3d start = o + double(r) * dv;
        for (int c = 0; c < g.size.width; ++c) {
            // Trilinear between the eight voxel centres round the point; a point beyond the
            // outermost centres (within half a voxel) takes the nearest face's values.
            std::array<int, 3> k0{};
            std::array<double, 3> f{};
            bool inside = true;
            for (int i = 0; i < 3 && inside; ++i) {
                const double x = start[i] + c * du[i];
                inside = x >= -0.5 && x <= m.size[i] - 0.5;
                const double xc = std::clamp(x, 0.0, double(m.size[i] - 1));
                k0[size_t(i)] = std::min(int(xc), std::max(0, m.size[i] - 2));
                f[size_t(i)] = m.size[i] > 1 ? xc - k0[size_t(i)] : 0.0;
            }
            if (!inside)
                continue;
            double v = 0;
            for (int corner = 0; corner < 8; ++corner) {
                std::int64_t offset = m.base;
                double wgt = 1;
                for (int i = 0; i < 3; ++i) {
                    const int bit = (corner >> i) & 1;
                    const int k = std::min(k0[size_t(i)] + bit, m.size[i] - 1);
                    wgt *= bit ? f[size_t(i)] : 1 - f[size_t(i)];
                    offset += std::int64_t(k) * m.stride[i];
                }
                if (wgt > 0)
                    v += wgt * data[offset];
            }
            row[c] = float(v / scale);
        }
    }
    return out;
}

core::Result<void> checkStackBudget(double slices, cv::Size size) {
    const double pixels = double(size.width) * size.height;
    const double bytes = slices * pixels * double(sizeof(std::int32_t));
    auto mib = [](double b) { return std::to_string(std::llround(b / (1 << 20))) + " MiB"; };
    const std::string plan =
        (slices < 1e15 ? std::to_string(std::llround(slices)) : "more than 1e15") + " slices of " +
        std::to_string(size.width) + " x " + std::to_string(size.height) + " px";
    if (!(slices <= kMaxStackSlices))
        return makeError(ErrorCode::InvalidArgument,
                         "the plan cuts " + plan + ", more than the " +
                             std::to_string(kMaxStackSlices) +
                             " slices a stack may hold (raise the interval)");
    if (pixels > double(kMaxSlicePixels))
        return makeError(ErrorCode::InvalidArgument, "the plan cuts " + plan + ": more than " +
                                                         std::to_string(kMaxSlicePixels) +
                                                         " px per slice (raise the pixel size)");
    if (bytes > double(kMaxStackBytes))
        return makeError(ErrorCode::InvalidArgument, "the plan cuts " + plan + ": " + mib(bytes) +
                                                         " of labels, beyond the budget of " +
                                                         mib(double(kMaxStackBytes)) +
                                                         " (raise the interval or the pixel size)");
    return {};
}

core::Result<std::vector<AtlasSlice>> sliceVolume(const core::Volume& volume, VolumeAxes axes,
                                                  const CuttingPlan& plan,
                                                  const SliceProgress& progress) {
    if (!(plan.intervalUm > 0) || !std::isfinite(plan.intervalUm))
        return makeError(ErrorCode::InvalidArgument, "interval_um must be a positive number");
    const Layout l = layout(plan.orientation);
    const double lastUm = volumeExtentUm(volume, axes)[l.normalAxis];
    std::vector<AtlasSlice> slices;
    CuttingPlane p{plan.orientation, plan.firstUm, plan.tiltColumnsDeg, plan.tiltRowsDeg,
                   plan.umPerPx};
    // Every plane has the first one's size (the tilts are the plan's): the whole stack is
    // known before a voxel is sampled.
    auto first = planeGeometry(volume, axes, p);
    if (!first)
        return first.error();
    const double planes =
        1 + std::max(0.0, std::floor((lastUm + 1e-6 - plan.firstUm) / plan.intervalUm));
    if (auto budget = checkStackBudget(planes, first->size); !budget)
        return budget.error();
    slices.reserve(std::size_t(planes));
    // Index-based positions: repeated addition would drift off the plan's grid.
    for (int i = 0;; ++i) {
        p.positionUm = plan.firstUm + i * plan.intervalUm;
        if (i > 0 && p.positionUm > lastUm + 1e-6)
            break;
        auto g = planeGeometry(volume, axes, p);
        if (!g)
            return g.error();
        auto labels = sampleLabels(volume, axes, *g);
        if (!labels)
            return labels.error();
        slices.push_back({std::move(*labels), *g});
        if (progress)
            progress(i + 1, static_cast<int>(planes));
    }
    return slices;
}

} // namespace slicestation::pipeline
