// Scan plans and daemon settings: both formats, every field's error named.
#include "slicestation/daemon/config/config_document.hpp"
#include "slicestation/daemon/config/daemon_settings.hpp"
#include "slicestation/daemon/config/scan_plan.hpp"
#include "slicestation/daemon/config/station_config.hpp"

#include <gtest/gtest.h>

#include <unistd.h>

#include <filesystem>
#include <fstream>

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
    if (!doc)
        return doc.error();
    return parseScanPlan(*doc, "plan.toml");
}

std::string errorOf(const std::string& text, DocumentFormat f = DocumentFormat::Toml) {
    auto p = planFrom(text, f);
    if (p)
        return "(accepted)";
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
    EXPECT_NE(errorOf("name = \"x\"\nslides = []").find("slides: expected a non-empty array"),
              std::string::npos);
    EXPECT_NE(errorOf("name = \"x\"\n[[slides]]\n[[slides.sections]]\ny_um = 1\n")
                  .find("slides[0].sections[0].x_um: missing"),
              std::string::npos);
    EXPECT_NE(errorOf("name = \"x\"\n[[slides]]\n[[slides.sections]]\nx_um = 1\ny_um = \"far\"\n")
                  .find("slides[0].sections[0].y_um: expected a number"),
              std::string::npos);
    EXPECT_NE(
        errorOf(
            "name = \"x\"\n[[slides]]\n[[slides.sections]]\nx_um = 1\ny_um = 1\natlas_slice = -2\n")
            .find("atlas_slice: -2 is outside"),
        std::string::npos);
    EXPECT_NE(errorOf("name = \"x\"\n[[slides]]\n[[slides.sections]]\nx_um = 1\ny_um = "
                      "1\natlas_slice = 1\natlas_position_um = 5\n")
                  .find("not both"),
              std::string::npos);
    EXPECT_NE(
        errorOf("name = \"x\"\n[[slides]]\n[[slides.sections]]\nname=\"a\"\nx_um = 1\ny_um = 1\n"
                "[[slides.sections]]\nname=\"a\"\nx_um = 2\ny_um = 1\n")
            .find("appears twice"),
        std::string::npos);
    EXPECT_NE(errorOf("name = \"x\"\n[[slides]\n").find("plan.toml:2"), std::string::npos);
    EXPECT_NE(errorOf("{\"name\": ", DocumentFormat::Json).find("not valid JSON"),
              std::string::npos);
}

TEST(ScanPlan, ResolveChecksStageLimitsAndTheAtlasStack) {
    const hw::StageLimits limits{{0, 75'000}, {0, 25'000}, hw::AxisRange{0, 5'000}};
    std::vector<double> positions;
    for (int i = 0; i < 80; ++i)
        positions.push_back(100.0 * i);
    auto p = planFrom(kPlanToml);
    ASSERT_TRUE(p);
    ASSERT_TRUE(resolveScanPlan(*p, limits, positions, "plan.toml"));
    EXPECT_EQ(p->sections[1].section.expectedSlice, 13); // 1330 um -> slice at 1300 um
    EXPECT_FALSE(p->sections[2].section.expectedSlice.has_value());

    auto far = planFrom(std::string(kPlanToml).replace(std::string(kPlanToml).find("y_um = 21000"),
                                                       12, "y_um = 26000"));
    ASSERT_TRUE(far);
    auto r = resolveScanPlan(*far, limits, positions, "plan.toml");
    ASSERT_FALSE(r);
    EXPECT_NE(r.error().message.find("slides[1].sections[0].y_um"), std::string::npos);

    auto beyond = planFrom(std::string(kPlanToml).replace(
        std::string(kPlanToml).find("atlas_slice = 12"), 16, "atlas_slice = 80"));
    ASSERT_TRUE(beyond);
    r = resolveScanPlan(*beyond, limits, positions, "plan.toml");
    ASSERT_FALSE(r);
    EXPECT_NE(r.error().message.find("atlas_slice: 80 is not in the atlas stack (slices 0..79)"),
              std::string::npos);
}

TEST(DaemonSettings, DefaultsSnapshotAndErrors) {
    auto doc = parseDocument(
        "[scan]\nobjective = \"4x\"\nexposure_us = 20000\n[scan.objectives.4x]\num_per_px = 8.0\n"
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
    EXPECT_DOUBLE_EQ(s->scan.maxTurnDeg, 180); // any way, unless the lab says otherwise

    // The lab's mounting rule: kept in the snapshot, range-checked.
    auto mounted = parseDocument("[scan]\num_per_px = 2\nmax_turn_deg = 45\n", DocumentFormat::Toml,
                                 "station.toml");
    auto m = parseDaemonSettings(*mounted, "station.toml");
    ASSERT_TRUE(m) << m.error().message;
    EXPECT_DOUBLE_EQ(m->scan.maxTurnDeg, 45);
    auto mBack = scanSettingsFromJson(toJson(m->scan), "snapshot");
    ASSERT_TRUE(mBack) << mBack.error().message;
    EXPECT_DOUBLE_EQ(mBack->maxTurnDeg, 45);
    auto overTurned = parseDocument("[scan]\num_per_px = 2\nmax_turn_deg = 200\n",
                                    DocumentFormat::Toml, "station.toml");
    auto o = parseDaemonSettings(*overTurned, "station.toml");
    ASSERT_FALSE(o);
    EXPECT_NE(o.error().message.find("scan.max_turn_deg"), std::string::npos) << o.error().message;

    auto noPixel =
        parseDocument("[scan]\nobjective = \"10x\"\n", DocumentFormat::Toml, "station.toml");
    auto e = parseDaemonSettings(*noPixel, "station.toml");
    ASSERT_FALSE(e);
    EXPECT_NE(e.error().message.find("scan.objectives.10x.um_per_px"), std::string::npos);
    auto shortToken = parseDocument("[daemon]\ntoken = \"abc\"\n[scan]\num_per_px = 2\n",
                                    DocumentFormat::Toml, "st");
    e = parseDaemonSettings(*shortToken, "st");
    ASSERT_FALSE(e);
    EXPECT_NE(e.error().message.find("daemon.token"), std::string::npos);
    auto badPort = parseDocument("[daemon]\nhttp_port = 70000\n[scan]\num_per_px = 2\n",
                                 DocumentFormat::Toml, "st");
    e = parseDaemonSettings(*badPort, "st");
    ASSERT_FALSE(e);
    EXPECT_NE(e.error().message.find("daemon.http_port"), std::string::npos);
    auto singular = parseDocument("[scan]\num_per_px = 2\n[scan.objectives.default]\num_per_px = "
                                  "2\ncamera_to_stage = [1, 1, 1, 1]\n",
                                  DocumentFormat::Toml, "st");
    e = parseDaemonSettings(*singular, "st");
    ASSERT_FALSE(e);
    EXPECT_NE(e.error().message.find("camera_to_stage"), std::string::npos);
}

// Issue 20: hostile documents. Each of these crashed, aborted or was silently accepted before.

namespace {

std::string nested(std::size_t levels, const std::string& open, const std::string& close) {
    std::string s;
    s.reserve(levels * (open.size() + close.size()));
    for (std::size_t i = 0; i < levels; ++i)
        s += open;
    for (std::size_t i = 0; i < levels; ++i)
        s += close;
    return s;
}

std::string docError(const std::string& text, DocumentFormat f,
                     const std::string& origin = "plan") {
    auto d = parseDocument(text, f, origin);
    if (d)
        return "(accepted)";
    EXPECT_EQ(d.error().code, core::ErrorCode::InvalidArgument);
    return d.error().message;
}

const char* kSection = "name = \"x\"\n[[slides]]\n[[slides.sections]]\nx_um = 1\ny_um = 1\n";

} // namespace

TEST(HostileDocument, DeepNestingIsRefusedBeforeAnyParserRecurses) {
    // 300'000 levels overflowed the stack in nlohmann's parse, copy or dump.
    EXPECT_NE(docError(nested(300'000, "[", "]"), DocumentFormat::Json)
                  .find("plan: nested deeper than 64 levels"),
              std::string::npos);
    EXPECT_NE(docError("{\"name\": " + nested(300'000, "{\"a\":", "}") + "}", DocumentFormat::Json)
                  .find("nested deeper than 64"),
              std::string::npos);
    // Brackets inside strings are not nesting.
    EXPECT_EQ(docError("{\"name\": \"" + std::string(1000, '[') + "\\\"[\"}", DocumentFormat::Json),
              "(accepted)");
    // Exactly at the limit is accepted, one more is not.
    EXPECT_EQ(docError(nested(64, "[", "]"), DocumentFormat::Json), "(accepted)");
    EXPECT_NE(docError(nested(65, "[", "]"), DocumentFormat::Json).find("nested deeper"),
              std::string::npos);

    // TOML nests through brackets and through the parts of dotted keys and table headers.
    std::string dotted = "a";
    for (int i = 0; i < 300'000; ++i)
        dotted += ".a";
    EXPECT_NE(docError(dotted + " = 1\n", DocumentFormat::Toml).find("nested deeper"),
              std::string::npos);
    EXPECT_NE(docError("[" + dotted + "]\n", DocumentFormat::Toml).find("nested deeper"),
              std::string::npos);
    EXPECT_NE(
        docError("a = " + nested(300'000, "[", "]") + "\n", DocumentFormat::Toml).find("plan"),
        std::string::npos);
    EXPECT_NE(docError("a = " + nested(100, "{b=", "}") + "\n", DocumentFormat::Toml)
                  .find("nested deeper"),
              std::string::npos);
    // Headers of 60 parts and a 60-part key inside: 120 levels, refused on the converted tree.
    std::string sixty = "a";
    for (int i = 0; i < 59; ++i)
        sixty += ".a";
    EXPECT_NE(docError("[" + sixty + "]\n" + sixty + " = 1\n", DocumentFormat::Toml)
                  .find("nested deeper"),
              std::string::npos);
    // Ordinary documents with dots in values, strings and comments are not nesting.
    EXPECT_EQ(docError("v = [1.5, 2.5, 3.5]\ns = \"a.b.c.d.e.f.g.h.i.j\" # a.b.c\nt = '''x.y'''\n",
                       DocumentFormat::Toml),
              "(accepted)");
    auto ok = planFrom(kPlanToml);
    EXPECT_TRUE(ok) << ok.error().message;
}

TEST(HostileDocument, NumbersOutOfRangeAreAnErrorNotAnAbort) {
    // nlohmann throws out_of_range 406 for 1e400; it ended in std::terminate.
    const std::string plan =
        R"({"name": "x", "slides": [{"sections": [{"x_um": 1e400, "y_um": 0}]}]})";
    EXPECT_NE(docError(plan, DocumentFormat::Json).find("plan: not valid JSON"), std::string::npos);
    EXPECT_NE(docError("{\"a\": -1e99999}", DocumentFormat::Json).find("plan"), std::string::npos);
    // TOML allows inf and nan; a plan does not.
    EXPECT_NE(docError(std::string(kSection) + "width_um = inf\n", DocumentFormat::Toml)
                  .find("plan: slides[0].sections[0].width_um: expected a finite number"),
              std::string::npos);
    EXPECT_NE(
        docError(std::string(kSection) + "width_um = nan\n", DocumentFormat::Toml).find("finite"),
        std::string::npos);
    EXPECT_NE(docError("x = 99999999999999999999\n", DocumentFormat::Toml).find("plan"),
              std::string::npos);
    // An unsigned integer beyond int64 is out of range, not wrapped to a negative slice.
    EXPECT_NE(
        errorOf(
            R"({"name": "x", "slides": [{"sections": [{"x_um": 1, "y_um": 1, "atlas_slice": 18446744073709551615}]}]})",
            DocumentFormat::Json)
            .find("atlas_slice: 18446744073709551615 is outside [0, 100000]"),
        std::string::npos);
    // A wrong type names the field, with a bounded excerpt of the value.
    const std::string big = R"({"name": "x", "slides": ")" + std::string(100'000, 'n') + R"("})";
    const std::string e = errorOf(big, DocumentFormat::Json);
    EXPECT_NE(e.find("slides: expected a non-empty array"), std::string::npos) << e.substr(0, 200);
    EXPECT_LT(e.size(), 300u);
    EXPECT_LT(errorOf(R"({"name": [")" + std::string(100'000, 'n') + R"("]})", DocumentFormat::Json)
                  .size(),
              300u);
}

TEST(HostileDocument, SizeIsLimited) {
    const std::string huge = "name = \"" + std::string(std::size_t{4} << 20, 'x') + "\"\n";
    EXPECT_NE(docError(huge, DocumentFormat::Toml).find("a document may have"), std::string::npos);
    const auto file = std::filesystem::temp_directory_path() /
                      ("slst-huge-" + std::to_string(::getpid()) + ".toml");
    {
        std::ofstream out(file, std::ios::binary);
        out << huge;
    }
    auto r = readDocument(file);
    std::filesystem::remove(file);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, core::ErrorCode::InvalidArgument);
    EXPECT_NE(r.error().message.find("larger than the 4194304 bytes"), std::string::npos)
        << r.error().message;
}

TEST(StrictKeys, MisspeltPlanKeysAreRefusedWithTheNearestKnownOne) {
    EXPECT_NE(errorOf(std::string(kSection) + "atlas_slcie = 3\n")
                  .find("plan.toml: slides[0].sections[0]: unknown key \"atlas_slcie\"; did you "
                        "mean \"atlas_slice\"?"),
              std::string::npos);
    EXPECT_NE(
        errorOf(std::string(kSection) + "widht_um = 3\n")
            .find("slides[0].sections[0]: unknown key \"widht_um\"; did you mean \"width_um\"?"),
        std::string::npos);
    EXPECT_NE(
        errorOf("name = \"x\"\n[[slides]]\nnmae = \"a\"\n[[slides.sections]]\nx_um = 1\ny_um = 1\n")
            .find("slides[0]: unknown key \"nmae\"; did you mean \"name\"?"),
        std::string::npos);
    EXPECT_NE(
        errorOf("name = \"x\"\ncolour = 3\n[[slides]]\n[[slides.sections]]\nx_um = 1\ny_um = 1\n")
            .find("(document): unknown key \"colour\" (known: name, slides)"),
        std::string::npos);
}

TEST(PlanNames, LengthAndCharactersAreLimited) {
    const auto named = [](const std::string& name) {
        return "name = \"x\"\n[[slides]]\n[[slides.sections]]\nname = \"" + name +
               "\"\nx_um = 1\ny_um = 1\n";
    };
    EXPECT_EQ(errorOf(named(std::string(64, 'a'))), "(accepted)");
    EXPECT_NE(errorOf(named(std::string(300, 'a')))
                  .find("slides[0].sections[0].name: 300 bytes is longer than the 64"),
              std::string::npos);
    EXPECT_NE(errorOf(named("a\\tb")).find("control characters"), std::string::npos);
    EXPECT_NE(errorOf(named("a/b")).find("'/'"), std::string::npos);
    EXPECT_NE(errorOf(named("..")).find("only dots"), std::string::npos);
    EXPECT_NE(errorOf(named(".")).find("only dots"), std::string::npos);
    EXPECT_NE(errorOf(named("")).find("must not be empty"), std::string::npos);
    EXPECT_EQ(errorOf(named("s-01.b \xc3\xa9")), "(accepted)");
    EXPECT_NE(
        errorOf(
            "name = \"x\"\n[[slides]]\nname = \"../up\"\n[[slides.sections]]\nx_um = 1\ny_um = 1\n")
            .find("slides[0].name"),
        std::string::npos);
    EXPECT_NE(errorOf("name = \"" + std::string(300, 'r') +
                      "\"\n[[slides]]\n[[slides.sections]]\nx_um = 1\ny_um = 1\n")
                  .find("name: 300 bytes is longer than the 256"),
              std::string::npos);
}

TEST(ScanPlan, ResolveRefusesTilesOutsideTheStageLimits) {
    const hw::StageLimits limits{{0, 75'000}, {0, 25'000}, hw::AxisRange{0, 5'000}};
    const std::vector<double> positions{0, 100, 200};
    // The centre is inside; the section reaches 4 mm past the Y limit.
    auto p = planFrom("name = \"x\"\n[[slides]]\nname = \"sl\"\n[[slides.sections]]\nname = "
                      "\"wide\"\nx_um = 10000\n"
                      "y_um = 20000\nwidth_um = 8000\nheight_um = 18000\n");
    ASSERT_TRUE(p) << p.error().message;
    auto r = resolveScanPlan(*p, limits, positions, "plan.toml");
    ASSERT_FALSE(r);
    EXPECT_NE(r.error().message.find(
                  "slides[0].sections[0].y_um: section \"wide\" on sl reaches Y 11000 .. 29000 um "
                  "(y_um +- height_um/2), outside the stage's Y limits [0, 25000] um"),
              std::string::npos)
        << r.error().message;
    auto left = planFrom("name = \"x\"\n[[slides]]\n[[slides.sections]]\nx_um = 3000\ny_um = "
                         "100\nwidth_um = 6001\n");
    ASSERT_TRUE(left);
    r = resolveScanPlan(*left, limits, positions, "plan.toml");
    ASSERT_FALSE(r);
    EXPECT_NE(r.error().message.find(
                  "sections[0].x_um: section \"s1-1\" on slide-1 reaches X -0.5 .. 6000.5 um"),
              std::string::npos)
        << r.error().message;
    // Exactly at the limits is inside.
    auto edge = planFrom("name = \"x\"\n[[slides]]\n[[slides.sections]]\nx_um = 3000\ny_um = "
                         "12500\nwidth_um = 6000\n"
                         "height_um = 25000\n");
    ASSERT_TRUE(edge);
    EXPECT_TRUE(resolveScanPlan(*edge, limits, positions, "plan.toml"));
}

namespace {

std::string settingsError(const std::string& toml) {
    auto doc = parseDocument(toml, DocumentFormat::Toml, "station.toml");
    if (!doc)
        return doc.error().message;
    auto s = parseDaemonSettings(*doc, "station.toml");
    if (s)
        return "(accepted)";
    EXPECT_EQ(s.error().code, core::ErrorCode::InvalidArgument);
    return s.error().message;
}

std::string stationError(const std::string& toml) {
    auto s = parseStationConfig(toml, "station.toml");
    if (s)
        return "(accepted)";
    EXPECT_EQ(s.error().code, core::ErrorCode::InvalidArgument);
    return s.error().message;
}

const char* kSimStage = "[stage]\ndriver = \"sim\"\n[stage.axes.x]\nmin_um = 0\nmax_um = 75000\n"
                        "[stage.axes.y]\nmin_um = 0\nmax_um = 25000\n";

} // namespace

TEST(StrictKeys, MisspeltStationKeysAreRefused) {
    const std::string scan = "[scan]\num_per_px = 2\n";
    EXPECT_EQ(settingsError(scan), "(accepted)");
    EXPECT_NE(
        settingsError(scan + "min_free_mbb = 3\n")
            .find(
                "station.toml: scan: unknown key \"min_free_mbb\"; did you mean \"min_free_mb\"?"),
        std::string::npos);
    EXPECT_NE(settingsError(scan + "exposur_us = 3\n").find("did you mean \"exposure_us\"?"),
              std::string::npos);
    EXPECT_NE(settingsError("[daemon]\ntokn = \"0123456789abcdef\"\n" + scan)
                  .find("daemon: unknown key \"tokn\"; did you mean \"token\"?"),
              std::string::npos);
    EXPECT_NE(settingsError("[daemon]\nhttp_bnd = \"0.0.0.0\"\n" + scan)
                  .find("did you mean \"http_bind\"?"),
              std::string::npos);
    EXPECT_NE(settingsError("[daemn]\n" + scan)
                  .find("(document): unknown key \"daemn\"; did you mean \"daemon\"?"),
              std::string::npos);
    EXPECT_NE(
        settingsError("[scan]\nobjective = \"4x\"\n[scan.objectives.4x]\num_per_pix = 2\n")
            .find("scan.objectives.4x: unknown key \"um_per_pix\"; did you mean \"um_per_px\"?"),
        std::string::npos);
    EXPECT_NE(settingsError("[scan]\nobjectives = 3\num_per_px = 2\n")
                  .find("scan.objectives: expected a table"),
              std::string::npos);

    EXPECT_EQ(stationError(kSimStage), "(accepted)");
    EXPECT_NE(stationError(std::string(kSimStage) + "[stage.axes.x]\n").find("station.toml"),
              std::string::npos);
    EXPECT_NE(stationError("[stage]\ndriver = \"sim\"\nspeeed_um_per_s = 3\n[stage.axes.x]\nmin_um "
                           "= 0\nmax_um = 1\n"
                           "[stage.axes.y]\nmin_um = 0\nmax_um = 1\n")
                  .find("station.toml: stage: unknown key \"speeed_um_per_s\"; did you mean "
                        "\"speed_um_per_s\"?"),
              std::string::npos);
    EXPECT_NE(stationError(std::string(kSimStage) + "[camera]\ndriver = \"sim\"\nexposur_us = 5\n")
                  .find("camera: unknown key \"exposur_us\"; did you mean \"exposure_us\"?"),
              std::string::npos);
    EXPECT_NE(stationError(std::string(kSimStage) +
                           "[camera]\ndriver = \"sim\"\n[camera.sim]\ncolums = 5\n")
                  .find("camera.sim: unknown key \"colums\"; did you mean \"columns\"?"),
              std::string::npos);
    EXPECT_NE(
        stationError(
            std::string(kSimStage) +
            "[camera]\ndriver = \"sim\"\n[[camera.sim.sections]]\nap_fraction = 0.5\nsed = 1\n")
            .find("camera.sim.sections[0]: unknown key \"sed\"; did you mean \"seed\"?"),
        std::string::npos);
    EXPECT_NE(stationError(
                  "[stage]\ndriver = \"sim\"\n[stage.axes.x]\nmin_um = 0\nmax_um = 1\nmax_mu = 2\n"
                  "[stage.axes.y]\nmin_um = 0\nmax_um = 1\n")
                  .find("stage.axes.x: unknown key \"max_mu\"; did you mean \"max_um\"?"),
              std::string::npos);
    EXPECT_NE(stationError(std::string(kSimStage) + "[stage.axes.w]\nmin_um = 0\nmax_um = 1\n")
                  .find("stage.axes: unknown key \"w\""),
              std::string::npos);
    // A key of another driver or transport is not silently ignored either.
    EXPECT_NE(
        stationError(
            "[stage]\ndriver = \"sim\"\nhost = \"h\"\n[stage.axes.x]\nmin_um = 0\nmax_um = 1\n"
            "[stage.axes.y]\nmin_um = 0\nmax_um = 1\n")
            .find("stage.host: only for driver = \"modbus\""),
        std::string::npos);
    EXPECT_NE(stationError(std::string(kSimStage) +
                           "[camera]\ndriver = \"sim\"\ndevice = \"/dev/video1\"\n")
                  .find("camera.device: only for driver = \"v4l2\""),
              std::string::npos);
    EXPECT_NE(stationError(std::string(kSimStage) + "[camra]\n")
                  .find("(document): unknown key \"camra\"; did you mean \"camera\"?"),
              std::string::npos);
}

TEST(StationRanges, EveryNumberIsBoundedBeforeItIsCast) {
    const auto stage = [](const std::string& extra) {
        return "[stage]\ndriver = \"modbus\"\ntransport = \"tcp\"\nhost = \"h\"\n" + extra +
               "[stage.axes.x]\nslave = 1\nsteps_per_um = 2\nmin_um = 0\nmax_um = 1\n"
               "[stage.axes.y]\nslave = 2\nsteps_per_um = 2\nmin_um = 0\nmax_um = 1\n";
    };
    EXPECT_EQ(stationError(stage("")), "(accepted)");
    EXPECT_NE(stationError(stage("retries = 1e300\n")).find("stage.retries"), std::string::npos);
    EXPECT_NE(stationError(stage("port = 502.5\n")).find("stage.port"), std::string::npos);
    EXPECT_NE(stationError(stage("move_timeout_s = 1e300\n"))
                  .find("stage.move_timeout_s: must be <= 3600"),
              std::string::npos);
    EXPECT_NE(stationError(stage("settle_ms = 1e300\n")).find("stage.settle_ms"),
              std::string::npos);
    EXPECT_NE(stationError(stage("device = \"/dev/ttyUSB0\"\n"))
                  .find("stage.device: only for transport = \"rtu\""),
              std::string::npos);
    EXPECT_NE(stationError(std::string(kSimStage) +
                           "[camera]\ndriver = \"sim\"\n[[camera.sim.sections]]\nap_fraction = "
                           "0.5\nseed = 1e300\n")
                  .find("camera.sim.sections[0].seed"),
              std::string::npos);
    // A virtual slide that would not fit in memory is refused before it is allocated.
    EXPECT_NE(stationError(std::string(kSimStage) +
                           "[camera]\ndriver = \"sim\"\n[camera.sim]\nslide_um_per_px = 0.1\n"
                           "section_pitch_um = 1000000\nsection_width_um = 1000\n")
                  .find("the virtual slide would be"),
              std::string::npos);
    EXPECT_NE(settingsError("[scan]\num_per_px = 2\nstart_z_um = 1e300\n").find("scan.start_z_um"),
              std::string::npos);
}

TEST(DaemonSettings, RegisterFalseIsRefusedNotIgnored) {
    EXPECT_NE(settingsError("[scan]\num_per_px = 2\nregister = false\n")
                  .find("scan.register: false is not supported"),
              std::string::npos);
    EXPECT_EQ(settingsError("[scan]\num_per_px = 2\nregister = true\n"), "(accepted)");
    // A snapshot stored by an older version is read as it is, so that its run still resumes.
    auto doc = parseDocument("[scan]\num_per_px = 2\n", DocumentFormat::Toml, "st");
    ASSERT_TRUE(doc);
    auto s = parseDaemonSettings(*doc, "st");
    ASSERT_TRUE(s);
    auto snap = toJson(s->scan);
    snap["register"] = false;
    EXPECT_TRUE(scanSettingsFromJson(snap, "snapshot"));
}
