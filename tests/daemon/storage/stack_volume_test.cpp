// The volume a stack was cut from, read back to cut planes the stack does not hold
// (daemon/storage/stack_volume.hpp): the planes equal what `atlas slice` cuts, straight and
// tilted, and a stack or volume that cannot give them is refused with a message naming it.
#include "slicestation/daemon/cli/atlas_command.hpp"
#include "slicestation/daemon/storage/stack_volume.hpp"

#include "../../common/test_dir.hpp"

#include <gtest/gtest.h>
#include <opencv2/core.hpp>

#include <cmath>
#include <cstdint>
#include <fstream>

using namespace slicestation;
using namespace slicestation::daemon;
namespace fs = std::filesystem;

namespace {

/// A 40 x 30 x 24 voxel brain of 50 um (Allen axes: AP, DV, LR), raw uint16: nested ellipsoids
/// of three ids, and one more id on the left half, so that planes differ with position and tilt.
void writeVolume(const fs::path& path, int sizeAp = 40) {
    const int s0 = sizeAp, s1 = 30, s2 = 24;
    std::vector<std::uint16_t> v(std::size_t(s0) * s1 * s2, 0);
    for (int k = 0; k < s2; ++k)
        for (int j = 0; j < s1; ++j)
            for (int i = 0; i < s0; ++i) {
                const double x = (i - s0 / 2.0) / (s0 * 0.45), y = (j - s1 / 2.0) / (s1 * 0.4),
                             z = (k - s2 / 2.0) / (s2 * 0.45);
                const double r = std::sqrt(x * x + y * y + z * z);
                std::uint16_t id = r < 0.4 ? 10 : r < 0.7 ? 20 : r < 1 ? 30 : 0;
                if (id != 0 && k < s2 / 2 && y < 0)
                    id = 40;
                v[std::size_t(i + s0 * (j + s1 * k))] = id;
            }
    std::ofstream out(path, std::ios::binary);
    out << "NRRD0004\ntype: unsigned short\ndimension: 3\nsizes: " << s0 << " " << s1 << " " << s2
        << "\nspacings: 50 50 50\nendian: little\nencoding: raw\n\n";
    out.write(reinterpret_cast<const char*>(v.data()), std::streamsize(v.size() * 2));
}

class StackVolumeTest : public testing_dir::TempDirTest {
protected:
    StackVolumeTest() : TempDirTest("stack-volume") {}

    AtlasStack cut(const std::string& name, double firstUm, double lr, double dv) {
        AtlasSliceRequest rq;
        rq.volume = dir_ / "brain.nrrd";
        rq.regions = "all";
        rq.umPerPx = 50;
        rq.intervalUm = 200;
        rq.firstUm = firstUm;
        rq.tiltLrDeg = lr;
        rq.tiltDvDeg = dv;
        rq.output = dir_ / name;
        auto r = runAtlasSlice(rq);
        EXPECT_TRUE(r) << r.error().message;
        auto s = readStack(dir_ / name);
        EXPECT_TRUE(s) << s.error().message;
        return s ? *s : AtlasStack{};
    }

    static bool same(const cv::Mat& a, const cv::Mat& b) {
        return a.size() == b.size() && a.type() == b.type() && cv::countNonZero(a != b) == 0;
    }
};

} // namespace

TEST_F(StackVolumeTest, PlanesAreCutAsTheStacksStraightAndTilted) {
    writeVolume(dir_ / "brain.nrrd");
    const AtlasStack stack = cut("stack", 300, 0, 0);
    ASSERT_GE(stack.slices.size(), 5u);
    auto v = readStackVolume(stack);
    ASSERT_TRUE(v) << v.error().message;
    EXPECT_FALSE(v->major);
    EXPECT_FALSE(v->templateVolume.has_value());

    // Straight: the stack's own slice, pixel for pixel, with its frame.
    const StackSlice& s3 = stack.slices[3];
    auto plane = cutStackPlane(*v, s3.positionUm, 0, 0);
    ASSERT_TRUE(plane) << plane.error().message;
    auto labels = readStackSlice(stack, 3);
    ASSERT_TRUE(labels);
    EXPECT_TRUE(same(plane->labels, *labels));
    EXPECT_EQ(plane->geometry.originUm, s3.geometry.originUm);
    EXPECT_EQ(plane->geometry.normal, s3.geometry.normal);

    // Tilted: the first slice of a stack cut at that tilt from that position.
    const AtlasStack tilted = cut("tilted", s3.positionUm, 8, -6);
    auto leaning = cutStackPlane(*v, s3.positionUm, 8, -6);
    ASSERT_TRUE(leaning) << leaning.error().message;
    auto tiltedLabels = readStackSlice(tilted, 0);
    ASSERT_TRUE(tiltedLabels);
    EXPECT_TRUE(same(leaning->labels, *tiltedLabels));
    EXPECT_FALSE(same(leaning->labels, plane->labels)) << "the tilt changes the plane";
    EXPECT_EQ(leaning->geometry.normal, tilted.slices[0].geometry.normal);

    // The matching features of the same plane.
    auto f = stackPlaneFeatures(*v, s3.positionUm, 8, -6, 100);
    ASSERT_TRUE(f) << f.error().message;
    EXPECT_DOUBLE_EQ(f->positionUm, s3.positionUm);

    // A plane beyond the volume's ends.
    auto outside = cutStackPlane(*v, 1e5, 0, 0);
    ASSERT_FALSE(outside);
    EXPECT_EQ(outside.error().code, core::ErrorCode::OutOfRange);
}

TEST_F(StackVolumeTest, AStackOrVolumeThatCannotGivePlanesIsRefusedByName) {
    writeVolume(dir_ / "brain.nrrd");
    AtlasStack stack = cut("stack", 300, 0, 0);
    ASSERT_FALSE(stack.slices.empty());
    const auto refused = [&](const AtlasStack& s, const fs::path& volume,
                             const std::string& needle) {
        auto v = readStackVolume(s, volume);
        ASSERT_FALSE(v) << needle;
        EXPECT_NE(v.error().message.find(needle), std::string::npos) << v.error().message;
    };
    // Another volume than the stack's (another size), a missing one.
    writeVolume(dir_ / "other.nrrd", 44);
    refused(stack, dir_ / "other.nrrd", "size differs");
    refused(stack, dir_ / "missing.nrrd", "missing.nrrd");
    // A manifest whose source is not a volume's, or malformed.
    AtlasStack builtin = stack;
    builtin.source["kind"] = "builtin";
    refused(builtin, {}, "cut from a volume");
    AtlasStack malformed = stack;
    malformed.source["axes"] = 7;
    refused(malformed, {}, "manifest source");
    AtlasStack nameless = stack;
    nameless.source.erase("volume");
    refused(nameless, {}, "names no volume");
    // A major-region stack without its ontology.
    AtlasStack major = stack;
    major.source["regions"] = "major";
    major.source["ontology"] = "";
    refused(major, {}, "ontology");
}
