// Virtual slicing: exact planes, tilted planes against an independent reference, ids, collapse.
#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/pipeline/atlas_slicing.hpp"

#include <gtest/gtest.h>
#include <opencv2/imgproc.hpp>

#include <cmath>
#include <filesystem>
#include <set>
#include <utility>
#include <vector>

using namespace slicestation;
using namespace slicestation::pipeline;
namespace fs = std::filesystem;

namespace {

const fs::path kAtlasDir = fs::path(SLST_SHARED_DIR) / "atlas" / "allen-ccf-2017";

/// The 100 um annotation, read once for the suite (nullptr when ../shared is absent).
const core::Volume* annotation100() {
    static const core::Volume* volume = [] {
        auto v = core::readNrrd(kAtlasDir / "annotation_100.nrrd");
        return v ? new core::Volume(std::move(*v)) : nullptr; // lives for the test program
    }();
    return volume;
}

#define REQUIRE_ALLEN(v)                                                                           \
    const core::Volume* v = annotation100();                                                       \
    if (!v)                                                                                        \
    GTEST_SKIP() << "no Allen annotation at " << kAtlasDir << " (SLST_SHARED_DIR)"

/// A small volume with every voxel distinct, Allen axes, anisotropic spacing.
core::Volume rampVolume() {
    core::Volume v;
    v.sizes = {12, 9, 15}; // AP, DV, LR
    v.spacingUm = {20, 30, 25};
    v.data.resize(12 * 9 * 15);
    for (size_t i = 0; i < v.data.size(); ++i)
        v.data[i] = std::uint32_t(i + 1);
    return v;
}

/// The same voxels in QuickNII order: x = LR, y = last - AP, z = last - DV.
core::Volume asQuickNii(const core::Volume& a) {
    core::Volume q;
    q.sizes = {a.sizes[2], a.sizes[0], a.sizes[1]};
    q.spacingUm = {a.spacingUm[2], a.spacingUm[0], a.spacingUm[1]};
    q.data.resize(a.data.size());
    for (int ap = 0; ap < a.sizes[0]; ++ap)
        for (int dv = 0; dv < a.sizes[1]; ++dv)
            for (int lr = 0; lr < a.sizes[2]; ++lr) {
                const int y = q.sizes[1] - 1 - ap, z = q.sizes[2] - 1 - dv;
                q.data[size_t(lr + q.sizes[0] * (y + q.sizes[1] * z))] = a.at(ap, dv, lr);
            }
    return q;
}

/// Independent reference: the plane's axes by Rodrigues rotations, then the nearest voxel.
int referenceLabel(const core::Volume& v, int normalAxis, int colAxis, int rowAxis,
                   double positionUm, double tiltColDeg, double tiltRowDeg, double umPerPx,
                   cv::Size size, int col, int row) {
    auto e = [](int axis) {
        cv::Vec3d x(0, 0, 0);
        x[axis] = 1;
        return x;
    };
    const cv::Vec3d n0 = e(normalAxis), u0 = e(colAxis), v0 = e(rowAxis);
    // Rodrigues' formula: R = I + sin(t) K + (1 - cos(t)) K^2 for the unit axis k.
    auto rot = [](cv::Vec3d k, double deg) {
        const double t = deg * CV_PI / 180;
        const cv::Matx33d kx(0, -k[2], k[1], k[2], 0, -k[0], -k[1], k[0], 0);
        return cv::Matx33d::eye() + std::sin(t) * kx + (1 - std::cos(t)) * (kx * kx);
    };
    const cv::Matx33d r1 = rot(n0.cross(u0), tiltColDeg);
    const cv::Vec3d n1 = r1 * n0;
    const cv::Matx33d r2 = rot(n1.cross(v0), tiltRowDeg);
    const cv::Vec3d u = r2 * (r1 * u0), w = r2 * v0;
    cv::Vec3d c;
    for (int i = 0; i < 3; ++i)
        c[i] = 0.5 * (v.sizes[i] - 1) * v.spacingUm[i];
    c[normalAxis] = positionUm;
    const cv::Vec3d p = c + (col - 0.5 * (size.width - 1)) * umPerPx * u +
                        (row - 0.5 * (size.height - 1)) * umPerPx * w;
    int k[3];
    for (int i = 0; i < 3; ++i) {
        k[i] = int(std::lround(p[i] / v.spacingUm[i]));
        if (k[i] < 0 || k[i] >= v.sizes[i])
            return 0;
    }
    return int(v.at(k[0], k[1], k[2]));
}

} // namespace

TEST(AtlasSlicing, UntiltedCoronalSliceIsTheVolumePlane) {
    REQUIRE_ALLEN(v);
    for (int ap = 0; ap < v->sizes[0]; ap += 7) {
        auto g = planeGeometry(*v, VolumeAxes::Allen,
                               {PlaneOrientation::Coronal, ap * 100.0, 0, 0, 100});
        ASSERT_TRUE(g.ok()) << g.error().message;
        auto s = sampleLabels(*v, VolumeAxes::Allen, *g);
        auto ref = coronalPlane(*v, VolumeAxes::Allen, ap);
        ASSERT_TRUE(s.ok() && ref.ok());
        ASSERT_EQ(s->size(), ref->size());
        EXPECT_EQ(cv::countNonZero(*s != *ref), 0) << "AP index " << ap;
    }
}

TEST(AtlasSlicing, FinerPixelsKeepEveryIdOfThePlane) {
    REQUIRE_ALLEN(v);
    auto g = planeGeometry(*v, VolumeAxes::Allen, {PlaneOrientation::Coronal, 6000, 0, 0, 25});
    ASSERT_TRUE(g.ok());
    EXPECT_EQ(g->size, cv::Size(v->sizes[2] * 4, v->sizes[1] * 4));
    auto s = sampleLabels(*v, VolumeAxes::Allen, *g);
    auto ref = coronalPlane(*v, VolumeAxes::Allen, 60);
    ASSERT_TRUE(s.ok() && ref.ok());
    cv::Mat down;
    cv::resize(*s, down, ref->size(), 0, 0, cv::INTER_NEAREST);
    std::set<int> a(s->begin<int>(), s->end<int>()), b(ref->begin<int>(), ref->end<int>());
    EXPECT_EQ(a, b); // ids preserved: no interpolated values, none lost
    EXPECT_GT(a.size(), 50u);
}

TEST(AtlasSlicing, TiltedPlanesMatchAnIndependentReference) {
    REQUIRE_ALLEN(v);
    struct Case {
        PlaneOrientation o;
        int n, c, r;
        double pos, ta, tb, um;
    };
    const Case cases[] = {{PlaneOrientation::Coronal, 0, 2, 1, 6500, 5, -3, 50},
                          {PlaneOrientation::Coronal, 0, 2, 1, 3000, -8, 0, 70},
                          {PlaneOrientation::Sagittal, 2, 0, 1, 4000, 4, 6, 50},
                          {PlaneOrientation::Horizontal, 1, 2, 0, 4000, -5, 7, 60}};
    for (const Case& k : cases) {
        auto g = planeGeometry(*v, VolumeAxes::Allen, {k.o, k.pos, k.ta, k.tb, k.um});
        ASSERT_TRUE(g.ok()) << g.error().message;
        auto s = sampleLabels(*v, VolumeAxes::Allen, *g);
        ASSERT_TRUE(s.ok());
        int differ = 0, brain = 0;
        for (int y = 0; y < s->rows; ++y)
            for (int x = 0; x < s->cols; ++x) {
                const int ref =
                    referenceLabel(*v, k.n, k.c, k.r, k.pos, k.ta, k.tb, k.um, s->size(), x, y);
                differ += ref != s->at<int>(y, x);
                brain += ref != 0;
            }
        // Only rounding ties at voxel faces may differ between the two constructions.
        EXPECT_LT(differ, s->total() / 1000 + 1) << toString(k.o) << " at " << k.pos;
        EXPECT_GT(brain, int(s->total() / 5)) << toString(k.o);
    }
}

TEST(AtlasSlicing, QuickNiiAxesGiveTheSameSlicesAsAllenAxes) {
    const core::Volume a = rampVolume();
    const core::Volume q = asQuickNii(a);
    for (auto o :
         {PlaneOrientation::Coronal, PlaneOrientation::Sagittal, PlaneOrientation::Horizontal}) {
        const CuttingPlane p{o, 100, 7, -4, 11};
        auto ga = planeGeometry(a, VolumeAxes::Allen, p);
        auto gq = planeGeometry(q, VolumeAxes::QuickNii, p);
        ASSERT_TRUE(ga.ok() && gq.ok());
        auto sa = sampleLabels(a, VolumeAxes::Allen, *ga);
        auto sq = sampleLabels(q, VolumeAxes::QuickNii, *gq);
        ASSERT_TRUE(sa.ok() && sq.ok());
        EXPECT_EQ(cv::countNonZero(*sa != *sq), 0) << toString(o);
        EXPECT_GT(cv::countNonZero(*sa), 0);
    }
    // Dorsal on top in QuickNII too: row 0 of an untilted coronal plane is DV index 0.
    auto g = planeGeometry(q, VolumeAxes::QuickNii, {PlaneOrientation::Coronal, 40, 0, 0, 25});
    auto s = sampleLabels(q, VolumeAxes::QuickNii, *g);
    EXPECT_EQ(std::uint32_t(s->at<int>(0, 3)), a.at(2, 0, 3));
}

TEST(AtlasSlicing, PlanGivesEvenlySpacedPlanesInsideTheVolume) {
    const core::Volume a = rampVolume(); // AP extent 0..220 um
    auto stack = sliceVolume(a, VolumeAxes::Allen, {PlaneOrientation::Coronal, 10, 50, 0, 0, 20});
    ASSERT_TRUE(stack.ok());
    ASSERT_EQ(stack->size(), 5u); // 10, 60, 110, 160, 210
    EXPECT_DOUBLE_EQ(stack->back().geometry.positionUm, 210);
    EXPECT_DOUBLE_EQ(stack->front().geometry.normal[0], 1);
}

TEST(AtlasSlicing, ProgressIsReportedAfterEveryPlane) {
    const core::Volume a = rampVolume();
    std::vector<std::pair<int, int>> calls;
    auto stack = sliceVolume(a, VolumeAxes::Allen, {PlaneOrientation::Coronal, 10, 50, 0, 0, 20},
                             [&](int done, int total) { calls.emplace_back(done, total); });
    ASSERT_TRUE(stack.ok());
    ASSERT_EQ(calls.size(), 5u);
    for (int i = 0; i < 5; ++i)
        EXPECT_EQ(calls[size_t(i)], std::make_pair(i + 1, 5));
}

TEST(AtlasSlicing, BadPlanesAreClearErrors) {
    const core::Volume a = rampVolume();
    auto out = planeGeometry(a, VolumeAxes::Allen, {PlaneOrientation::Coronal, 400, 0, 0, 20});
    ASSERT_FALSE(out.ok());
    EXPECT_EQ(out.error().code, core::ErrorCode::OutOfRange);
    EXPECT_NE(out.error().message.find("outside the volume"), std::string::npos);
    EXPECT_EQ(
        planeGeometry(a, VolumeAxes::Allen, {PlaneOrientation::Coronal, 0, 0, 0, 0}).error().code,
        core::ErrorCode::InvalidArgument);
    EXPECT_EQ(
        planeGeometry(a, VolumeAxes::Allen, {PlaneOrientation::Coronal, 0, 75, 0, 10}).error().code,
        core::ErrorCode::InvalidArgument);
    core::Volume noSpacing = a;
    noSpacing.spacingUm = {0, 0, 0};
    EXPECT_EQ(planeGeometry(noSpacing, VolumeAxes::Allen, {PlaneOrientation::Coronal, 0, 0, 0, 10})
                  .error()
                  .code,
              core::ErrorCode::InvalidArgument);
    EXPECT_EQ(
        sliceVolume(a, VolumeAxes::Allen, {PlaneOrientation::Coronal, 0, 0, 0, 0, 10}).error().code,
        core::ErrorCode::InvalidArgument);
    EXPECT_FALSE(parsePlaneOrientation("oblique").ok());
    core::Volume big = a;
    big.data[0] = 0x90000000u;
    auto g = planeGeometry(big, VolumeAxes::Allen, {PlaneOrientation::Coronal, 0, 0, 0, 20});
    EXPECT_EQ(sampleLabels(big, VolumeAxes::Allen, *g).error().code,
              core::ErrorCode::InvalidArgument);
}

TEST(AtlasSlicing, PlansBeyondTheMemoryBudgetAreRefusedBeforeSampling) {
    const core::Volume a = rampVolume(); // 220 um along AP, 375 x 270 um in plane
    // 0.01 um apart: 22001 planes, more than a stack may hold.
    auto many = sliceVolume(a, VolumeAxes::Allen, {PlaneOrientation::Coronal, 0, 0.01, 0, 0, 20});
    ASSERT_FALSE(many.ok());
    EXPECT_EQ(many.error().code, core::ErrorCode::InvalidArgument);
    EXPECT_NE(many.error().message.find("22001 slices"), std::string::npos) << many.error().message;
    EXPECT_NE(many.error().message.find(std::to_string(kMaxStackSlices)), std::string::npos);
    // 0.02 um/px: 18750 x 13500 px planes, more than a plane may hold; 1e-6 um/px would
    // overflow int.
    for (double umPerPx : {0.02, 1e-6}) {
        auto fine =
            sliceVolume(a, VolumeAxes::Allen, {PlaneOrientation::Coronal, 0, 100, 0, 0, umPerPx});
        ASSERT_FALSE(fine.ok()) << umPerPx;
        EXPECT_EQ(fine.error().code, core::ErrorCode::InvalidArgument);
        EXPECT_NE(fine.error().message.find("raise the pixel size"), std::string::npos)
            << fine.error().message;
    }
    // 0.1 um apart at 0.05 um/px: 2201 planes of 7500 x 5400 px, 332 GiB in all.
    auto heavy = sliceVolume(a, VolumeAxes::Allen, {PlaneOrientation::Coronal, 0, 0.1, 0, 0, 0.05});
    ASSERT_FALSE(heavy.ok());
    EXPECT_NE(heavy.error().message.find("MiB of labels, beyond the budget of 2048 MiB"),
              std::string::npos)
        << heavy.error().message;
    EXPECT_TRUE(checkStackBudget(1000, {456, 320}).ok());
}

TEST(AtlasSlicing, MajorRegionCollapseOfARealSlice) {
    REQUIRE_ALLEN(v);
    auto onto = core::readOntologyCsv(kAtlasDir / "structure_tree_safe_2017.csv");
    ASSERT_TRUE(onto.ok()) << onto.error().message;
    // Known structures: layer 5 of primary motor cortex, medial habenula (Epithalamus inside
    // Thalamus), corpus callosum, lateral ventricle.
    cv::Mat known = (cv::Mat_<int>(1, 5) << 648, 483, 776, 81, 672);
    const cv::Mat k = collapseLabels(known, *onto, majorRegionIds(), 8);
    EXPECT_EQ(k.at<int>(0, 0), 315);
    EXPECT_EQ(k.at<int>(0, 1), 958);
    EXPECT_EQ(k.at<int>(0, 2), 1009);
    EXPECT_EQ(k.at<int>(0, 3), 73);
    EXPECT_EQ(k.at<int>(0, 4), 672);
    // A striatal-level coronal plane (AP 5.0 mm) holds cortex, caudoputamen and fibre tracts.
    auto g = planeGeometry(*v, VolumeAxes::Allen, {PlaneOrientation::Coronal, 5000, 0, 0, 50});
    auto s = sampleLabels(*v, VolumeAxes::Allen, *g);
    ASSERT_TRUE(s.ok());
    const cv::Mat c = collapseLabels(*s, *onto, majorRegionIds(), 8);
    std::set<int> ids(c.begin<int>(), c.end<int>());
    for (int id : {315, 672, 1009, 73})
        EXPECT_TRUE(ids.count(id)) << id;
    EXPECT_LE(ids.size(), majorRegionIds().size() + 2);             // + outside (0) and other (8)
    EXPECT_EQ(cv::countNonZero(c != 0), cv::countNonZero(*s != 0)); // the brain keeps its shape
}
