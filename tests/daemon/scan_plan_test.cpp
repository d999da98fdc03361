// Scan plans and daemon settings: both formats, every field's error named.
#include "slicestation/daemon/config_document.hpp"
#include "slicestation/daemon/daemon_settings.hpp"
#include "slicestation/daemon/scan_plan.hpp"

#include <gtest/gtest.h>

using namespace slicestation;
using namespace slicestation::daemon;

namespace {

const char* kPlanToml = R"(
name = "mouse-42"
[[slides]]
name = "slide-01"
[[slides.sections]]
x_um = 11000
y_um = 9000
atlas_slice = 12
[[slides.sections]]
name = "big"
x_um = 23000
y_um = 9000
width_um = 14000
height_um = 9000
atlas_position_um = 1330
[[slides]]
[[slides.sections]]
x_um = 11000
y_um = 21000
)";

core::Result<ScanPlan> planFrom(const std::string& text, DocumentFormat f = DocumentFormat::Toml) {
    auto doc = parseDocument(text, f, "plan.toml");
    if (!doc) return doc.error();
    return parseScanPlan(*doc, "plan.toml");
}

std::string errorOf(const std::string& text, DocumentFormat f = DocumentFormat::Toml) {
    auto p = planFrom(text, f);
    if (p) return "(accepted)";
    EXPECT_EQ(p.error().code, core::ErrorCode::InvalidArgument);
    return p.error().message;
}

} // namespace

TEST(ScanPlan, TomlAndJsonGiveTheSamePlan) {
    auto t = planFrom(kPlanToml);
    ASSERT_TRUE(t) << t.error().message;
    EXPECT_EQ(t->name, "mouse-42");
    ASSERT_EQ(t->sections.size(), 3u);
    EXPECT_EQ(t->sections[0].section.name, "s1-1");
    EXPECT_EQ(t->sections[0].section.expectedSlice, 12);
    EXPECT_EQ(t->sections[1].section.name, "big");
    EXPECT_DOUBLE_EQ(t->sections[1].section.widthUm, 14000);
    EXPECT_EQ(t->sections[1].atlasPositionUm, 1330);
    EXPECT_EQ(t->sections[2].section.slideName, "slide-2");
    EXPECT_EQ(t->sections[2].section.slideIndex, 1);

    auto j = planFrom(t->document.dump(), DocumentFormat::Json);
    ASSERT_TRUE(j) << j.error().message;
    EXPECT_EQ(j->sections.size(), 3u);
    EXPECT_EQ(j->sections[1].section.name, "big");
}

TEST(ScanPlan, ErrorsNameTheField) {
    EXPECT_NE(errorOf("name = 3").find("name: expected a string"), std::string::npos);
    EXPECT_NE(errorOf("name = \"x\"").find("slides: missing"), std::string::npos);
    EXPECT_NE(errorOf("name = \"x\"\nslides = []").find("slides: expected a non-empty array"), std::string::npos);
    EXPECT_NE(errorOf("name = \"x\"\n[[slides]]\n[[slides.sections]]\ny_um = 1\n").find("slides[0].sections[0].x_um: missing"),
              std::string::npos);
    EXPECT_NE(errorOf("name = \"x\"\n[[slides]]\n[[slides.sections]]\nx_um = 1\ny_um = \"far\"\n")
                  .find("slides[0].sections[0].y_um: expected a number"),
              std::string::npos);
    EXPECT_NE(errorOf("name = \"x\"\n[[slides]]\n[[slides.sections]]\nx_um = 1\ny_um = 1\natlas_slice = -2\n")
                  .find("atlas_slice: -2 is outside"),
              std::string::npos);
    EXPECT_NE(errorOf("name = \"x\"\n[[slides]]\n[[slides.sections]]\nx_um = 1\ny_um = 1\natlas_slice = 1\natlas_position_um = 5\n")
                  .find("not both"),
              std::string::npos);
    EXPECT_NE(errorOf("name = \"x\"\n[[slides]]\n[[slides.sections]]\nname=\"a\"\nx_um = 1\ny_um = 1\n"
                      "[[slides.sections]]\nname=\"a\"\nx_um = 2\ny_um = 1\n")
                  .find("appears twice"),
              std::string::npos);
    EXPECT_NE(errorOf("name = \"x\"\n[[slides]\n").find("plan.toml:2"), std::string::npos);
    EXPECT_NE(errorOf("{\"name\": ", DocumentFormat::Json).find("not valid JSON"), std::string::npos);
}

TEST(ScanPlan, ResolveChecksStageLimitsAndTheAtlasStack) {
    const hw::StageLimits limits{{0, 75'000}, {0, 25'000}, hw::AxisRange{0, 5'000}};
    std::vector<double> positions;
    for (int i = 0; i < 80; ++i) positions.push_back(100.0 * i);
    auto p = planFrom(kPlanToml);
    ASSERT_TRUE(p);
    ASSERT_TRUE(resolveScanPlan(*p, limits, positions, "plan.toml"));
    EXPECT_EQ(p->sections[1].section.expectedSlice, 13); // 1330 um -> slice at 1300 um
    EXPECT_FALSE(p->sections[2].section.expectedSlice.has_value());

    auto far = planFrom(std::string(kPlanToml).replace(std::string(kPlanToml).find("y_um = 21000"), 12, "y_um = 26000"));
    ASSERT_TRUE(far);
    auto r = resolveScanPlan(*far, limits, positions, "plan.toml");
    ASSERT_FALSE(r);
    EXPECT_NE(r.error().message.find("slides[1].sections[0].y_um"), std::string::npos);

    auto beyond = planFrom(std::string(kPlanToml).replace(std::string(kPlanToml).find("atlas_slice = 12"), 16, "atlas_slice = 80"));
    ASSERT_TRUE(beyond);
    r = resolveScanPlan(*beyond, limits, positions, "plan.toml");
    ASSERT_FALSE(r);
    EXPECT_NE(r.error().message.find("atlas_slice: 80 is not in the atlas stack (slices 0..79)"), std::string::npos);
}

TEST(DaemonSettings, DefaultsSnapshotAndErrors) {
    auto doc = parseDocument("[scan]\nobjective = \"4x\"\nexposure_us = 20000\n[scan.objectives.4x]\num_per_px = 8.0\n"
                             "camera_to_stage = [0, 1, -1, 0]\n[daemon]\ntoken = \"0123456789abcdef\"\n",
                             DocumentFormat::Toml, "station.toml");
    ASSERT_TRUE(doc);
    auto s = parseDaemonSettings(*doc, "station.toml");
    ASSERT_TRUE(s) << s.error().message;
    EXPECT_EQ(s->httpBind, "127.0.0.1");
    EXPECT_EQ(s->scan.objective.name, "4x");
    EXPECT_DOUBLE_EQ(s->scan.objective.umPerPx, 8.0);
    EXPECT_EQ(s->scan.camera.exposureUs, 20000);
    // The snapshot restores to the same settings.
    auto back = scanSettingsFromJson(toJson(s->scan), "snapshot");
    ASSERT_TRUE(back) << back.error().message;
    EXPECT_EQ(toJson(*back), toJson(s->scan));

    auto noPixel = parseDocument("[scan]\nobjective = \"10x\"\n", DocumentFormat::Toml, "station.toml");
    auto e = parseDaemonSettings(*noPixel, "station.toml");
    ASSERT_FALSE(e);
    EXPECT_NE(e.error().message.find("scan.objectives.10x.um_per_px"), std::string::npos);
    auto shortToken = parseDocument("[daemon]\ntoken = \"abc\"\n[scan]\num_per_px = 2\n", DocumentFormat::Toml, "st");
    e = parseDaemonSettings(*shortToken, "st");
    ASSERT_FALSE(e);
    EXPECT_NE(e.error().message.find("daemon.token"), std::string::npos);
    auto badPort = parseDocument("[daemon]\nhttp_port = 70000\n[scan]\num_per_px = 2\n", DocumentFormat::Toml, "st");
    e = parseDaemonSettings(*badPort, "st");
    ASSERT_FALSE(e);
    EXPECT_NE(e.error().message.find("daemon.http_port"), std::string::npos);
    auto singular = parseDocument("[scan]\num_per_px = 2\n[scan.objectives.default]\num_per_px = 2\ncamera_to_stage = [1, 1, 1, 1]\n",
                                  DocumentFormat::Toml, "st");
    e = parseDaemonSettings(*singular, "st");
    ASSERT_FALSE(e);
    EXPECT_NE(e.error().message.find("camera_to_stage"), std::string::npos);
}
