// A section's results for other tools (docs/results.md), against ground truth: a section
// generated from a slice of a stack cut from the Allen CCFv3 100 um annotation, registered,
// then its saved mapping, CCF coordinates, QuickNII/VisuAlign slice and QuPath GeoJSON checked
// against the in-memory registration and against the QuickNII 25 um volume itself.
#include "slicestation/core/image_file.hpp"
#include "slicestation/core/nrrd.hpp"
#include "slicestation/daemon/cli/atlas_command.hpp"
#include "slicestation/daemon/export/run_export.hpp"
#include "slicestation/daemon/export/section_export.hpp"
#include "slicestation/daemon/station/registration_service.hpp"
#include "slicestation/sim/section_generator.hpp"

#include <gtest/gtest.h>
#include <opencv2/imgproc.hpp>

#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>

using namespace slicestation;
using namespace slicestation::daemon;
namespace fs = std::filesystem;
using nlohmann::json;

namespace {

const fs::path kShared = SLST_SHARED_DIR;
const fs::path kAllen = kShared / "atlas" / "allen-ccf-2017";

struct Registered {
    fs::path dir;
    AtlasStack stack;
    int slice = 0;
    sim::GeneratedSection section;
    RegisteredSection result;
};

/// One registration shared by the tests (about a second).
Registered* registered = nullptr;

class SectionExportTest : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        auto* r = new Registered;
        r->dir = fs::temp_directory_path() / ("slst-export-" + std::to_string(::getpid()));
        fs::remove_all(r->dir);
        fs::create_directories(r->dir / "out");
        AtlasSliceRequest sq;
        sq.volume = kAllen / "annotation_100.nrrd";
        sq.ontology = kAllen / "structure_tree_safe_2017.csv";
        sq.intervalUm = 1000;
        sq.firstUm = 500;
        sq.umPerPx = 50;
        sq.regions = "all"; // leaf ids, as the QuickNII volume holds them
        sq.output = r->dir / "stack";
        auto made = runAtlasSlice(sq);
        ASSERT_TRUE(made) << made.error().message;
        auto stack = readStack(sq.output);
        ASSERT_TRUE(stack) << stack.error().message;
        r->stack = *stack;
        r->slice = 6; // 6500 um: cortex, striatum, thalamus, both hemispheres
        auto labels = readStackSlice(r->stack, r->slice);
        ASSERT_TRUE(labels);
        sim::GeneratorOptions go;
        go.seed = 7;
        go.imageSize = {900, 700};
        go.landmarkCount = 300;
        auto gen = sim::generateSection(*labels, go);
        ASSERT_TRUE(gen) << gen.error().message;
        r->section = std::move(*gen);
        ASSERT_TRUE(core::writeImage(r->dir / "section.tif", r->section.image));

        RegisterRequest rq;
        auto path = stackSlicePath(r->stack, r->slice);
        ASSERT_TRUE(path);
        rq.atlas = *path;
        rq.atlasSlice = sliceFrame(r->stack, r->slice);
        rq.image = r->dir / "section.tif";
        rq.points = r->dir / "points.csv";
        rq.output = r->dir / "out" / "result.json";
        std::vector<cv::Point2d> pts;
        for (const auto& l : r->section.truth.landmarks)
            pts.push_back(l.image);
        auto reg = registerSectionFiles(
            rq, [&](const fs::path&) -> core::Result<std::vector<cv::Point2d>> { return pts; });
        ASSERT_TRUE(reg) << reg.error().message;
        r->result = std::move(*reg);
        registered = r;
    }
    static void TearDownTestSuite() {
        if (registered)
            fs::remove_all(registered->dir);
        delete registered;
        registered = nullptr;
    }
    void SetUp() override { ASSERT_NE(registered, nullptr) << "the shared registration failed"; }

    static SectionFiles files() {
        auto f = readResultFile(registered->dir / "out" / "result.json");
        EXPECT_TRUE(f) << f.error().message;
        return *f;
    }
    /// Points of the tissue on a grid (section px).
    static std::vector<cv::Point2d> tissuePoints(int step) {
        std::vector<cv::Point2d> out;
        const cv::Mat& m = registered->section.truth.tissueMask;
        for (int y = step / 2; y < m.rows; y += step)
            for (int x = step / 2; x < m.cols; x += step)
                if (m.at<std::uint8_t>(y, x))
                    out.push_back({double(x), double(y)});
        return out;
    }
    /// Section pixel size in atlas micrometres (for errors in section px).
    static double sectionUmPerPx() {
        return registered->stack.slices[std::size_t(registered->slice)].umPerPx *
               registered->result.registration.quality.scaleAtlasPxPerImagePx;
    }
};

TEST_F(SectionExportTest, TheSavedMappingMapsEveryPointAsTheRegistrationDid) {
    const SectionFiles f = files();
    EXPECT_EQ(f.result["mapping"]["field"], "result.field.tif");
    EXPECT_TRUE(fs::exists(registered->dir / "out" / "result.field.tif"));
    auto saved = readSavedMapping(f.result, f.resultDir);
    ASSERT_TRUE(saved) << saved.error().message;
    ASSERT_FALSE(saved->dx.empty()) << "the registration has a non-linear part";
    double worst = 0;
    std::vector<cv::Point2d> pts = tissuePoints(7);
    for (int y = 0; y < 700; y += 50) // also outside the tissue and on the borders
        for (int x = 0; x < 900; x += 50)
            pts.push_back({double(x), double(y)});
    pts.push_back({899, 699});
    for (const cv::Point2d& p : pts) {
        const cv::Point2d a = registered->result.registration.atlasFromImage(p);
        const cv::Point2d b = saved->atlasFromImage(p);
        worst = std::max(worst, cv::norm(a - b));
    }
    std::printf("saved mapping vs in-memory: %zu points, max difference %.2e atlas px\n",
                pts.size(), worst);
    EXPECT_LT(worst, 0.01);
    // The affine part alone, too.
    const cv::Matx23d a = saved->affineAtlasFromImage();
    const cv::Matx23d b = registered->result.registration.affineAtlasFromImage();
    EXPECT_LT(cv::norm(a - b), 1e-9);
}

TEST_F(SectionExportTest, PointsCarryCcfMicrometresOfTheirAtlasPixelAndTheResultItsProvenance) {
    const SectionFiles f = files();
    EXPECT_EQ(f.result["software"]["name"], "slicestation");
    EXPECT_FALSE(f.result["software"]["version"].get<std::string>().empty());
    EXPECT_EQ(f.result["image"]["file"], "../section.tif");
    EXPECT_EQ(f.result["atlas"]["file"], "../stack/slice-006.tif");
    const json& st = f.result["atlas"]["stack"];
    EXPECT_EQ(st["dir"], "../stack");
    EXPECT_EQ(st["index"], 6);
    EXPECT_DOUBLE_EQ(st["position_um"].get<double>(), 6500);
    EXPECT_TRUE(st["ccf"].get<bool>());
    const auto& geo = registered->stack.slices[6].geometry;
    const auto& landmarks = registered->section.truth.landmarks;
    ASSERT_EQ(f.result["points"].size(), landmarks.size());
    double sum = 0, worst = 0;
    for (std::size_t i = 0; i < landmarks.size(); ++i) {
        const json& p = f.result["points"][i];
        ASSERT_TRUE(p.contains("ccf_um"));
        const cv::Vec3d c(p["ccf_um"][0], p["ccf_um"][1], p["ccf_um"][2]);
        // Exactly the atlas frame of the stack at the mapped atlas pixel: AP is the plane's.
        const cv::Vec3d expect = geo.atlasUm(p["atlas_x"], p["atlas_y"]);
        EXPECT_LT(cv::norm(c - expect), 1e-6);
        EXPECT_DOUBLE_EQ(c[0], 6500);
        // Against the truth: where the generator took the landmark from.
        const cv::Vec3d truth = geo.atlasUm(landmarks[i].atlas.x, landmarks[i].atlas.y);
        const double e = cv::norm(c - truth);
        sum += e;
        worst = std::max(worst, e);
    }
    std::printf("ccf_um of %zu landmarks vs truth: mean %.1f um, max %.1f um\n", landmarks.size(),
                sum / landmarks.size(), worst);
    EXPECT_LT(sum / landmarks.size(), 100.0) << "registration error, two atlas px at 50 um";
}

TEST_F(SectionExportTest, TheQuickNiiAnchoringIsTheAffinePartAndTheMarkersTheRest) {
    const SectionFiles f = files();
    auto slice = quickNiiSliceOfResult(f, "section.png", 3);
    ASSERT_TRUE(slice) << slice.error().message;
    // The documented structure (VisuAlign's data/Slice.java): filename, nr, width, height,
    // anchoring of 9 numbers, markers of 4 numbers.
    const json series = json::parse(quickNiiSeries("run", json::array({*slice})).dump());
    EXPECT_EQ(series["target"], "ABA_Mouse_CCFv3_2017_25um.cutlas");
    EXPECT_EQ(series["target-resolution"], json({456, 528, 320}));
    const json& s = series["slices"][0];
    EXPECT_EQ(s["filename"], "section.png");
    EXPECT_EQ(s["nr"], 3);
    EXPECT_EQ(s["width"], 900);
    EXPECT_EQ(s["height"], 700);
    ASSERT_EQ(s["anchoring"].size(), 9u);
    ASSERT_GT(s["markers"].size(), 50u);
    for (const json& m : s["markers"])
        ASSERT_EQ(m.size(), 4u);

    const pipeline::Registration& reg = registered->result.registration;
    const auto& geo = registered->stack.slices[6].geometry;
    const cv::Matx23d A = reg.affineAtlasFromImage();
    const double voxelToPx = 25 / sectionUmPerPx();
    // Anchoring only = the affine part, exactly.
    double worstAffine = 0;
    auto anchoringOnly = VisuAlignMap::create(s, false);
    auto withMarkers = VisuAlignMap::create(s, true);
    ASSERT_TRUE(anchoringOnly && withMarkers);
    for (const cv::Point2d& p : tissuePoints(11)) {
        auto v = quickNiiVoxelOf(s, p, false); // the one-point form once per point here
        ASSERT_TRUE(v);
        const cv::Point2d a(A(0, 0) * p.x + A(0, 1) * p.y + A(0, 2),
                            A(1, 0) * p.x + A(1, 1) * p.y + A(1, 2));
        worstAffine = std::max(worstAffine, cv::norm(*v - quickNiiFromCcf(ccfUm(geo, a))));
    }
    EXPECT_LT(worstAffine, 1e-6);
    // With the markers: at the markers within a pixel of the full map; elsewhere measured.
    auto errorPx = [&](cv::Point2d p) {
        return cv::norm(withMarkers->voxelOf(p) -
                        quickNiiFromCcf(ccfUm(geo, reg.atlasFromImage(p)))) *
               voxelToPx;
    };
    double worstMarker = 0;
    for (const json& m : s["markers"])
        worstMarker =
            std::max(worstMarker, errorPx({m[2].get<double>() - 0.5, m[3].get<double>() - 0.5}));
    double sum = 0, worst = 0, sumAffine = 0;
    const auto pts = tissuePoints(5);
    for (const cv::Point2d& p : pts) {
        const double e = errorPx(p);
        sum += e;
        worst = std::max(worst, e);
        sumAffine += cv::norm(anchoringOnly->voxelOf(p) -
                              quickNiiFromCcf(ccfUm(geo, reg.atlasFromImage(p)))) *
                     voxelToPx;
    }
    std::printf("QuickNII/VisuAlign vs the station's map (section px): at %zu markers max %.3f; "
                "over %zu tissue points mean %.3f max %.3f with markers, mean %.3f anchoring "
                "only\n",
                s["markers"].size(), worstMarker, pts.size(), sum / pts.size(), worst,
                sumAffine / pts.size());
    EXPECT_LT(worstMarker, 1.0);
    EXPECT_LT(sum / pts.size(), sumAffine / pts.size()) << "markers bring it closer";
    EXPECT_LT(sum / pts.size(), 0.6 * sumAffine / pts.size());
}

TEST_F(SectionExportTest, TheQuickNiiCoordinatesLandInTheSameRegionsOfTheQuickNiiVolume) {
    // The convention check against data: the QuickNII-space 25 um annotation read at the voxel
    // the anchoring gives must hold the id the station's atlas slice has there.
    auto vol = core::readNrrd(kAllen / "annotation_25_quicknii.nrrd");
    ASSERT_TRUE(vol) << vol.error().message;
    ASSERT_EQ(vol->sizes, (std::array<int, 3>{456, 528, 320}));
    const SectionFiles f = files();
    auto slice = quickNiiSliceOfResult(f, "section.png", 1);
    ASSERT_TRUE(slice);
    auto atlasLabels = readStackSlice(registered->stack, registered->slice);
    ASSERT_TRUE(atlasLabels);
    auto visuAlign = VisuAlignMap::create(*slice, true);
    ASSERT_TRUE(visuAlign);
    const pipeline::Registration& reg = registered->result.registration;
    auto idAt = [&](cv::Vec3d q) -> std::uint32_t {
        const int x = int(std::floor(q[0])), y = int(std::floor(q[1])), z = int(std::floor(q[2]));
        if (x < 0 || y < 0 || z < 0 || x >= 456 || y >= 528 || z >= 320)
            return 0;
        return vol->at(x, y, z);
    };
    int n = 0, same = 0, sameUnflipped = 0;
    for (const cv::Point2d& p : tissuePoints(9)) {
        const cv::Point2d a = reg.atlasFromImage(p);
        const int ax = int(std::lround(a.x)), ay = int(std::lround(a.y));
        if (ax < 0 || ay < 0 || ax >= atlasLabels->cols || ay >= atlasLabels->rows)
            continue;
        const std::int32_t expect = atlasLabels->at<std::int32_t>(ay, ax);
        if (expect <= 0)
            continue;
        const cv::Vec3d v0 = visuAlign->voxelOf(p);
        const cv::Vec3d* v = &v0;
        ++n;
        same += idAt(*v) == std::uint32_t(expect);
        // The same point with dorsal-ventral not flipped: the wrong convention must show.
        sameUnflipped += idAt({(*v)[0], (*v)[1], 319 - (*v)[2]}) == std::uint32_t(expect);
    }
    std::printf("QuickNII volume id = station atlas id at %d of %d tissue points (%.1f%%); "
                "with DV unflipped %.1f%%\n",
                same, n, 100.0 * same / n, 100.0 * sameUnflipped / n);
    ASSERT_GT(n, 1000);
    // The 100 um grid the stack was cut from and the 25 um volume differ at region borders.
    EXPECT_GT(double(same) / n, 0.75);
    EXPECT_LT(double(sameUnflipped) / n, 0.5 * same / n);
}

double ringArea(const json& ring) {
    double a = 0;
    for (std::size_t i = 0; i + 1 < ring.size(); ++i)
        a += ring[i][0].get<double>() * ring[i + 1][1].get<double>() -
             ring[i + 1][0].get<double>() * ring[i][1].get<double>();
    return std::abs(a) / 2;
}

TEST_F(SectionExportTest, QuPathGetsClosedPolygonsPerRegionAndSideThatCoverTheMappedTissue) {
    const SectionFiles f = files();
    auto fc = qupathOfResult(f);
    ASSERT_TRUE(fc) << fc.error().message;
    const json j = json::parse(fc->dump());
    ASSERT_EQ(j["type"], "FeatureCollection");
    double polygonArea = 0;
    std::int64_t pixels = 0;
    int left = 0, right = 0, named = 0, regions = 0;
    for (const json& feat : j["features"]) {
        ASSERT_EQ(feat["type"], "Feature");
        const json& props = feat["properties"];
        ASSERT_TRUE(props["classification"]["name"].is_string());
        ASSERT_EQ(props["classification"]["color"].size(), 3u);
        if (props["classification"]["name"] == "Damage")
            continue;
        ++regions;
        const json& g = feat["geometry"];
        const json polys =
            g["type"] == "Polygon" ? json::array({g["coordinates"]}) : g["coordinates"];
        for (const json& poly : polys)
            for (std::size_t r = 0; r < poly.size(); ++r) {
                const json& ring = poly[r];
                ASSERT_GE(ring.size(), 4u);
                ASSERT_EQ(ring.front(), ring.back()) << "rings are closed";
                polygonArea += r == 0 ? ringArea(ring) : -ringArea(ring);
            }
        pixels += props["area_px"].get<std::int64_t>();
        left += props["hemisphere"] == "left";
        right += props["hemisphere"] == "right";
        named += props["acronym"].get<std::string>().find_first_not_of("0123456789") !=
                 std::string::npos;
        // The full hierarchy: the Allen path from the root (997) down to the region itself.
        const json& path = props["structure_id_path"];
        ASSERT_GE(path.size(), 1u) << props.dump();
        EXPECT_EQ(path.front(), 997);
        EXPECT_EQ(path.back(), props["allen_id"]);
        if (path.size() >= 2) { // the annotation also labels some voxels "root" itself
            EXPECT_EQ(props["parent_id"], path[path.size() - 2]);
        }
    }
    // The mapped atlas brain in the section.
    const cv::Mat labels = registered->result.registration.warpedLabels(
        *readStackSlice(registered->stack, registered->slice), {900, 700});
    const int mapped = cv::countNonZero(labels);
    std::printf("QuPath: %d region features (%d left, %d right), pixels %lld, polygon area %.0f, "
                "mapped brain %d px\n",
                regions, left, right, static_cast<long long>(pixels), polygonArea, mapped);
    EXPECT_GT(regions, 20) << "the full ontology: many leaf regions";
    EXPECT_EQ(named, regions) << "every id named from the ontology";
    // The stack (--regions all) lists every ancestor too, named, so counts roll up by name.
    for (std::uint32_t ancestor : {997u, 315u, 477u /* Striatum */, 549u /* Thalamus */}) {
        const StackRegion* r = findRegion(registered->stack, ancestor);
        ASSERT_NE(r, nullptr) << ancestor;
        EXPECT_FALSE(r->name.empty());
        EXPECT_EQ(r->path.back(), ancestor);
    }
    EXPECT_GT(left, 5);
    EXPECT_GT(right, 5);
    // Labels from the saved mapping at the section's size: the same pixels as the registration's.
    EXPECT_NEAR(double(pixels), mapped, 0.002 * mapped);
    // Polygons follow the pixels' edges: their area is the pixel count (pieces under 4 px are
    // left out).
    EXPECT_NEAR(polygonArea, double(pixels), 0.002 * double(pixels));
}

TEST_F(SectionExportTest, BadOrOldResultsAreRefusedNamingWhatIsWrong) {
    SectionFiles f = files();
    SectionFiles old = f;
    old.result.erase("mapping");
    auto m = readSavedMapping(old.result, old.resultDir);
    ASSERT_FALSE(m);
    EXPECT_EQ(m.error().code, core::ErrorCode::InvalidArgument);
    EXPECT_NE(m.error().message.find("mapping"), std::string::npos);
    SectionFiles lost = f;
    lost.result["mapping"]["field"] = "missing.field.tif";
    EXPECT_EQ(readSavedMapping(lost.result, lost.resultDir).error().code,
              core::ErrorCode::NotFound);
    SectionFiles resized = f;
    resized.result["mapping"]["field_cols"] = 3;
    auto r = readSavedMapping(resized.result, resized.resultDir);
    ASSERT_FALSE(r);
    EXPECT_NE(r.error().message.find("nodes"), std::string::npos) << r.error().message;
    SectionFiles builtin = f;
    builtin.result["atlas"]["stack"]["ccf"] = false;
    auto q = quickNiiSliceOfResult(builtin, "x.png", 1);
    ASSERT_FALSE(q);
    EXPECT_NE(q.error().message.find("CCF"), std::string::npos);
    SectionFiles plain = f;
    plain.result["atlas"].erase("stack");
    EXPECT_EQ(quickNiiSliceOfResult(plain, "x.png", 1).error().code,
              core::ErrorCode::InvalidArgument);
    EXPECT_FALSE(quickNiiVoxelOf(json{{"width", 10}}, {1, 1}, true));
    EXPECT_FALSE(quickNiiVoxelOf(json{{"width", 10},
                                      {"height", 10},
                                      {"anchoring", {0, 0, 0, 1, 0, 0, 0, 1, 0}},
                                      {"markers", {{1, 2, 3}}}},
                                 {1, 1}, true));
    EXPECT_EQ(readResultFile(f.resultDir / "nothing.json").error().code, core::ErrorCode::NotFound);
}

std::string run(const std::string& args) {
    const std::string cmd = std::string(SLICECTL_PATH) + " " + args + " 2>&1";
    std::string out;
    FILE* p = ::popen(cmd.c_str(), "r");
    char buf[4096];
    while (p && std::fgets(buf, sizeof buf, p))
        out += buf;
    const int st = p ? ::pclose(p) : -1;
    return std::to_string(WIFEXITED(st) ? WEXITSTATUS(st) : -1) + "|" + out;
}

TEST_F(SectionExportTest, ThePythonReaderOfTheDocsMapsThePointsAsTheStationDid) {
    // docs/examples/map_points.py: the standard library only (no numpy on the station).
    const std::string cmd = "python3 " +
                            (fs::path(SLST_SOURCE_DIR) / "docs/examples/map_points.py").string() +
                            " " + (registered->dir / "out" / "result.json").string() + " 2>&1";
    std::string out;
    FILE* p = ::popen(cmd.c_str(), "r");
    ASSERT_NE(p, nullptr);
    char buf[512];
    while (std::fgets(buf, sizeof buf, p))
        out += buf;
    ASSERT_EQ(::pclose(p), 0) << out;
    std::printf("%s", out.c_str());
    unsigned n = 0;
    double worst = -1;
    ASSERT_EQ(std::sscanf(out.c_str(), "points %u max_difference_atlas_px %lf", &n, &worst), 2)
        << out;
    EXPECT_EQ(n, registered->section.truth.landmarks.size());
    EXPECT_GE(worst, 0);
    EXPECT_LT(worst, 1e-6);
}

TEST_F(SectionExportTest, ARunExportsOneQuickNiiSliceAndOneQuPathCollectionPerRegisteredSection) {
    // A journal whose run has two sections: the first registered (the CCF result above, as the
    // daemon stores it: paths relative to the state directory), the second never captured.
    const fs::path state = registered->dir;
    auto journal = Journal::open(state / "journal.sqlite");
    ASSERT_TRUE(journal) << journal.error().message;
    std::vector<PlannedSection> plan(2);
    for (int i = 0; i < 2; ++i) {
        plan[std::size_t(i)].slideName = "slide 1";
        plan[std::size_t(i)].index = i;
        plan[std::size_t(i)].name = "s" + std::to_string(i + 1);
    }
    auto run = (*journal)->createRun("ccf-run", json::object(), json::object(), plan);
    ASSERT_TRUE(run) << run.error().message;
    auto secs = (*journal)->sections(*run);
    ASSERT_TRUE(secs);
    CaptureRecord c;
    c.sectionId = (*secs)[0].id;
    c.imagePath = "section.tif";
    c.umPerPx = 10;
    auto cap = (*journal)->recordCapture(c);
    ASSERT_TRUE(cap) << cap.error().message;
    RegistrationRecord rec;
    rec.captureId = *cap;
    rec.atlasSlice = registered->slice;
    rec.resultPath = "out/result.json";
    rec.result = files().result;
    ASSERT_TRUE((*journal)->recordRegistration(rec));

    auto q = exportRunResults(**journal, state, *run, "quicknii");
    ASSERT_TRUE(q) << q.error().message;
    const json series = json::parse(*q);
    EXPECT_EQ(series["name"], "ccf-run");
    EXPECT_EQ(series["target"], "ABA_Mouse_CCFv3_2017_25um.cutlas");
    ASSERT_EQ(series["slices"].size(), 1u);
    EXPECT_EQ(series["slices"][0]["filename"], "section.tif");
    EXPECT_EQ(series["slices"][0]["nr"], 1);
    auto one = quickNiiSliceOfResult(files(), "section.tif", 1);
    ASSERT_TRUE(one);
    EXPECT_EQ(series["slices"][0]["anchoring"], (*one)["anchoring"]);

    auto g = exportRunResults(**journal, state, *run, "qupath");
    ASSERT_TRUE(g) << g.error().message;
    const json collections = json::parse(*g);
    ASSERT_EQ(collections["sections"].size(), 1u);
    EXPECT_EQ(collections["sections"][0]["file"],
              std::to_string((*secs)[0].id) + "_slide_1_s1.geojson")
        << "names made safe for a file";
    EXPECT_EQ(collections["sections"][0]["feature_collection"]["type"], "FeatureCollection");

    EXPECT_EQ(exportRunResults(**journal, state, *run, "xml").error().code,
              core::ErrorCode::InvalidArgument);
    EXPECT_EQ(exportRunResults(**journal, state, *run + 1, "qupath").error().code,
              core::ErrorCode::NotFound);
}

TEST_F(SectionExportTest, SlicectlExportsOneResultForQuickNiiQuPathAndAsCsv) {
    const fs::path out = registered->dir / "out";
    const std::string result = (out / "result.json").string();
    auto r = run("export --result " + result + " --format quicknii --output " +
                 (out / "q.json").string());
    ASSERT_EQ(r.substr(0, 2), "0|") << r;
    std::ifstream qin(out / "q.json");
    const json q = json::parse(qin);
    EXPECT_EQ(q["slices"][0]["filename"], "section.tif");
    EXPECT_EQ(q["slices"][0]["anchoring"].size(), 9u);
    r = run("export --result " + result + " --format qupath --output " +
            (out / "s.geojson").string());
    ASSERT_EQ(r.substr(0, 2), "0|") << r;
    std::ifstream gin(out / "s.geojson");
    EXPECT_EQ(json::parse(gin)["type"], "FeatureCollection");
    r = run("export --result " + result + " --format csv");
    ASSERT_EQ(r.substr(0, 2), "0|") << r;
    EXPECT_NE(r.find("x,y,atlas_x,atlas_y,ccf_x_um,ccf_y_um,ccf_z_um\n"), std::string::npos);
    EXPECT_NE(r.find(",6500,"), std::string::npos) << "the plane's AP in every row";
    // Exit codes: usage, input.
    EXPECT_EQ(run("export --result " + result + " --format json").substr(0, 2), "1|");
    EXPECT_EQ(run("export --result " + result + " --format xml").substr(0, 1), "2")
        << "CLI11's own check of a value";
    EXPECT_EQ(run("export --result " + (out / "none.json").string() + " --format csv").substr(0, 2),
              "2|");
    EXPECT_EQ(run("export 3 --result " + result + " --format csv").substr(0, 2), "1|");
}

TEST_F(SectionExportTest, DenserMarkersFollowTheNonLinearMapCloser) {
    const SectionFiles f = files();
    auto saved = readSavedMapping(f.result, f.resultDir);
    ASSERT_TRUE(saved);
    const auto& geo = registered->stack.slices[6].geometry;
    const double voxelToPx = 25 / sectionUmPerPx();
    const auto pts = tissuePoints(9);
    std::printf("marker columns | markers | mean error px | max error px (%zu tissue points)\n",
                pts.size());
    double previous = 1e9;
    for (int cols : {0, 12, 32, 64}) {
        QuickNiiOptions o;
        o.markerColumns = cols;
        const json s = quickNiiSlice("x", 1, *saved, geo, o);
        auto map = VisuAlignMap::create(s, true);
        ASSERT_TRUE(map) << map.error().message;
        double sum = 0, worst = 0;
        for (const auto& p : pts) {
            const double e =
                cv::norm(map->voxelOf(p) - quickNiiFromCcf(ccfUm(geo, saved->atlasFromImage(p)))) *
                voxelToPx;
            sum += e;
            worst = std::max(worst, e);
        }
        std::printf("%14d | %7zu | %13.3f | %12.3f\n", cols,
                    s.value("markers", json::array()).size(), sum / pts.size(), worst);
        EXPECT_LT(sum / pts.size(), previous);
        previous = sum / pts.size();
    }
}

} // namespace
