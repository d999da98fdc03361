// Atlas stacks on disk: `atlas slice` on the real volume and the built-in atlas, manifest
// round trip, and the errors a user can provoke.
#include "slicestation/core/image_file.hpp"
#include "slicestation/core/nrrd.hpp"
#include "slicestation/daemon/cli/atlas_command.hpp"
#include "slicestation/daemon/storage/atlas_stack.hpp"
#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/sim/builtin_atlas.hpp"
#include "slicestation/sim/section_generator.hpp"

#include "../common/test_dir.hpp"

#include <gtest/gtest.h>

#include <nlohmann/json.hpp>

#include <algorithm>
#include <climits>
#include <filesystem>
#include <fstream>
#include <set>
#include <tuple>

using namespace slicestation;
using namespace slicestation::daemon;
namespace fs = std::filesystem;

namespace {

const fs::path kAtlasDir = fs::path(SLST_SHARED_DIR) / "atlas" / "allen-ccf-2017";

class AtlasStackTest : public ::testing::Test {
protected:
    void SetUp() override {
        dir_ = testing_dir::perTestPath("stack"); // runAtlasSlice makes it
        fs::remove_all(dir_);
    }
    void TearDown() override { fs::remove_all(dir_); }
    /// The real 100 um annotation sliced every 500 um from 300 um at 100 um per pixel into dir_.
    AtlasSliceRequest realVolumeRequest() const {
        AtlasSliceRequest rq;
        rq.volume = kAtlasDir / "annotation_100.nrrd";
        rq.ontology = kAtlasDir / "structure_tree_safe_2017.csv";
        rq.intervalUm = 500;
        rq.firstUm = 300;
        rq.umPerPx = 100;
        rq.output = dir_;
        return rq;
    }
    fs::path dir_;
};

} // namespace

TEST_F(AtlasStackTest, SlicesTheRealVolumeIntoAStackWithManifest) {
    if (!fs::exists(kAtlasDir / "annotation_100.nrrd"))
        GTEST_SKIP() << "no Allen annotation at " << kAtlasDir << " (SLST_SHARED_DIR)";
    AtlasSliceRequest rq = realVolumeRequest();
    auto r = runAtlasSlice(rq);
    ASSERT_TRUE(r.ok()) << r.error().message;
    auto stack = readStack(dir_);
    ASSERT_TRUE(stack.ok()) << stack.error().message;
    ASSERT_EQ(stack->slices.size(), 26u); // 300, 800, ... 12800 (the volume ends at 13100)
    EXPECT_DOUBLE_EQ(stack->slices[2].positionUm, 1300);
    EXPECT_DOUBLE_EQ(stack->slices[2].umPerPx, 100);
    EXPECT_EQ(stack->regions.size(), pipeline::majorRegionIds().size() + 1);
    EXPECT_EQ(stack->source.at("axes"), "allen");
    // Slice 10 (AP 5.3 mm) is the collapsed volume plane, ids as stored.
    auto labels = readStackSlice(*stack, 10);
    ASSERT_TRUE(labels.ok()) << labels.error().message;
    auto volume = core::readNrrd(rq.volume);
    auto onto = core::readOntologyCsv(rq.ontology);
    auto plane = pipeline::coronalPlane(*volume, pipeline::VolumeAxes::Allen, 53);
    const cv::Mat expected = pipeline::collapseLabels(*plane, *onto, pipeline::majorRegionIds(), 8);
    EXPECT_EQ(cv::countNonZero(*labels != expected), 0);
    // Beside it, the plane of every id (for the registration's region warp), and the ids of
    // the ventricles among them; the builtin atlas and `--regions all` stacks have none.
    EXPECT_EQ(stack->slices[10].idsFile, "ids-010.tif");
    auto ids = core::readImage(dir_ / "ids-010.tif");
    ASSERT_TRUE(ids.ok()) << ids.error().message;
    auto idLabels = pipeline::labelsFromImage(*ids);
    ASSERT_TRUE(idLabels.ok());
    EXPECT_EQ(cv::countNonZero(*idLabels != *plane), 0);
    ASSERT_FALSE(stack->ventricleIds.empty());
    for (std::int32_t id : stack->ventricleIds)
        EXPECT_TRUE(onto->isDescendantOf(std::uint32_t(id), pipeline::kVentricularSystemsId)) << id;
    {
        // Manifests come from outside: a bad id plane entry or ventricle list names itself.
        std::ifstream in(dir_ / "manifest.json");
        const nlohmann::json manifest = nlohmann::json::parse(in);
        const fs::path copy = dir_ / "bad-manifest";
        fs::create_directories(copy);
        for (const auto& [key, value, field] :
             {std::tuple{"ids", nlohmann::json("../ids-003.tif"), "slices[3].ids"},
              std::tuple{"ids", nlohmann::json(7), "slices[3].ids"},
              std::tuple{"ventricle_ids", nlohmann::json("81"), "ventricle_ids"},
              std::tuple{"ventricle_ids", nlohmann::json({81, -1}), "ventricle_ids"}}) {
            nlohmann::json m = manifest;
            if (std::string(key) == "ids")
                m["slices"][3]["ids"] = value;
            else
                m["ventricle_ids"] = value;
            std::ofstream(copy / "manifest.json") << m.dump();
            auto bad = readStack(copy);
            ASSERT_FALSE(bad.ok()) << value.dump();
            EXPECT_EQ(bad.error().code, core::ErrorCode::InvalidArgument);
            EXPECT_NE(bad.error().message.find(field), std::string::npos) << bad.error().message;
        }
    }
    // --regions all keeps every structure id.
    rq.regions = "all";
    rq.output = dir_ / "all";
    ASSERT_TRUE(runAtlasSlice(rq).ok());
    auto all = readStack(rq.output);
    auto raw = readStackSlice(*all, 10);
    ASSERT_TRUE(raw.ok());
    EXPECT_EQ(cv::countNonZero(*raw != *plane), 0);
    EXPECT_GT(all->regions.size(), 200u);
    EXPECT_TRUE(all->slices[10].idsFile.empty());
    EXPECT_TRUE(all->ventricleIds.empty());
}

TEST_F(AtlasStackTest, BuiltinAtlasIsAStackToo) {
    AtlasSliceRequest rq;
    rq.builtin = true;
    rq.intervalUm = 400;
    rq.output = dir_;
    auto r = runAtlasSlice(rq);
    ASSERT_TRUE(r.ok()) << r.error().message;
    auto stack = readStack(dir_ / "manifest.json");
    ASSERT_TRUE(stack.ok()) << stack.error().message;
    EXPECT_EQ(stack->slices.size(), 21u); // 0 .. 8000 um
    EXPECT_EQ(stack->source.at("kind"), "builtin");
    auto s = readStackSlice(*stack, 20);
    ASSERT_TRUE(s.ok());
    EXPECT_GT(cv::countNonZero(*s), 1000);
    EXPECT_FALSE(stack->regions.empty());
    EXPECT_TRUE(stack->slices[20].idsFile.empty());
    EXPECT_EQ(readStackSlice(*stack, 21).error().code, core::ErrorCode::OutOfRange);
}

TEST_F(AtlasStackTest, BadInputsAreClearErrors) {
    AtlasSliceRequest rq;
    rq.output = dir_;
    rq.volume = dir_ / "missing.nrrd";
    rq.ontology = dir_ / "missing.csv";
    EXPECT_EQ(runAtlasSlice(rq).error().code, core::ErrorCode::NotFound);
    rq.axes = "ras";
    auto axes = runAtlasSlice(rq);
    EXPECT_EQ(axes.error().code, core::ErrorCode::InvalidArgument);
    EXPECT_NE(axes.error().message.find("--axes"), std::string::npos);
    rq.axes = "allen";
    rq.regions = "some";
    EXPECT_NE(runAtlasSlice(rq).error().message.find("--regions"), std::string::npos);
    rq.regions = "major";
    rq.ontology.clear();
    EXPECT_NE(runAtlasSlice(rq).error().message.find("--ontology"), std::string::npos);
    // A file that is not a NRRD volume.
    fs::create_directories(dir_);
    std::ofstream(dir_ / "bad.nrrd") << "hello\n\n";
    rq.volume = dir_ / "bad.nrrd";
    rq.regions = "all";
    EXPECT_EQ(runAtlasSlice(rq).error().code, core::ErrorCode::InvalidArgument);
    if (fs::exists(kAtlasDir / "annotation_100.nrrd")) {
        rq.volume = kAtlasDir / "annotation_100.nrrd";
        rq.firstUm = 20000; // the volume is 13.1 mm long
        auto out = runAtlasSlice(rq);
        EXPECT_EQ(out.error().code, core::ErrorCode::OutOfRange);
        EXPECT_NE(out.error().message.find("outside the volume"), std::string::npos);
    }
    rq.builtin = true;
    rq.firstUm = 9000;
    EXPECT_EQ(runAtlasSlice(rq).error().code, core::ErrorCode::OutOfRange);
    // Manifests: missing, not JSON, missing field.
    EXPECT_EQ(readStack(dir_ / "nothing").error().code, core::ErrorCode::NotFound);
    std::ofstream(dir_ / "manifest.json") << "{not json";
    EXPECT_EQ(readStack(dir_).error().code, core::ErrorCode::InvalidArgument);
    std::ofstream(dir_ / "manifest.json") << R"({"slices": [{"index": 0, "file": "a.tif"}]})";
    auto missing = readStack(dir_);
    ASSERT_FALSE(missing.ok());
    EXPECT_NE(missing.error().message.find("position_um"), std::string::npos);
}

TEST_F(AtlasStackTest, EveryManifestFieldIsTypeAndRangeChecked) {
    fs::create_directories(dir_);
    const std::string good = R"("index": 0, "file": "slice-000.tif", "position_um": 0,
                                "normal": [1, 0, 0], "um_per_px": 25, "width": 456, "height": 320)";
    struct Case {
        std::string manifest, needle;
    };
    const std::vector<Case> cases{
        {"[]", "expected an object"},
        {R"({"slices": [5]})", "slices[0]"},
        {R"({"slices": [{)" + good + R"(, "height": "x"}]})", "slices[0].height"},
        {R"({"slices": [{)" + good + R"(, "width": -4}]})", "slices[0].width"},
        {R"({"slices": [{)" + good + R"(, "width": 1e12}]})", "slices[0].width"},
        {R"({"slices": [{)" + good + R"(, "index": 0.5}]})", "slices[0].index"},
        {R"({"slices": [{)" + good + R"(, "index": 3}]})", "slices[0].index"},
        {R"({"slices": [{)" + good + R"(, "file": 7}]})", "slices[0].file"},
        {R"({"slices": [{)" + good + R"(, "file": "../../etc/passwd"}]})", "slices[0].file"},
        {R"({"slices": [{)" + good + R"(, "file": "/etc/passwd"}]})", "slices[0].file"},
        {R"({"slices": [{)" + good + R"(, "position_um": "here"}]})", "slices[0].position_um"},
        {R"({"slices": [{)" + good + R"(, "position_um": 1e300}]})", "slices[0].position_um"},
        {R"({"slices": [{)" + good + R"(, "um_per_px": 0}]})", "slices[0].um_per_px"},
        {R"({"slices": [{)" + good + R"(, "um_per_px": null}]})", "slices[0].um_per_px"},
        {R"({"slices": [{)" + good + R"(, "normal": [1, "a", 0]}]})", "slices[0].normal[1]"},
        {R"({"slices": [{)" + good + R"(, "normal": {"x": 1}}]})", "slices[0].normal"},
        {R"({"slices": [{)" + good + R"(, "origin_um": [0, 0, 0]}]})", "slices[0].column_um"},
        {R"({"slices": [{)" + good + R"(}], "regions": {"id": 1}})", "regions"},
        {R"({"slices": [{)" + good + R"(}], "regions": [{"id": -3}]})", "regions[0].id"},
        {R"({"slices": [{)" + good + R"(}], "regions": [{"id": 5, "name": 5}]})",
         "regions[0].name"},
        {R"({"slices": [{)" + good + R"(}], "regions": [{"id": 5, "color": 7}]})",
         "regions[0].color"},
        {R"({"slices": [{)" + good + R"(}], "regions": [{"id": 5, "color": ""}]})",
         "regions[0].color"},
        {R"({"slices": [{)" + good + R"(}], "source": 5})", "source"},
    };
    for (const Case& c : cases) {
        std::ofstream(dir_ / "manifest.json") << c.manifest;
        auto stack = readStack(dir_);
        ASSERT_FALSE(stack.ok()) << c.manifest;
        EXPECT_EQ(stack.error().code, core::ErrorCode::InvalidArgument) << stack.error().message;
        EXPECT_NE(stack.error().message.find(c.needle), std::string::npos)
            << "'" << stack.error().message << "' should name " << c.needle;
        EXPECT_NE(stack.error().message.find("manifest.json"), std::string::npos);
    }
    std::ofstream(dir_ / "manifest.json")
        << R"({"slices": [{)" + good + R"(}], "regions": [{"id": 5, "color": "#A0b0C0"}]})";
    auto ok = readStack(dir_);
    ASSERT_TRUE(ok.ok()) << ok.error().message;
    EXPECT_EQ(ok->slices.front().geometry.size, cv::Size(456, 320));
    EXPECT_EQ(ok->regions.front().colorRgb, 0xA0B0C0u);
}

TEST_F(AtlasStackTest, PlansBeyondTheBudgetAndOutOfRangeOptionsAreRefused) {
    AtlasSliceRequest rq;
    rq.builtin = true;
    rq.output = dir_;
    rq.intervalUm = 1; // 8001 planes of 456 x 320 px: 4.6 GB of labels
    auto big = runAtlasSlice(rq);
    ASSERT_FALSE(big.ok());
    EXPECT_EQ(big.error().code, core::ErrorCode::InvalidArgument);
    EXPECT_NE(big.error().message.find("8001 slices of 456 x 320 px"), std::string::npos)
        << big.error().message;
    EXPECT_NE(big.error().message.find("budget of 2048 MiB"), std::string::npos);
    EXPECT_FALSE(fs::exists(dir_ / "manifest.json"));
    // The request's own ranges hold for every caller, not only for slicectl's options.
    for (auto bad : {+[](AtlasSliceRequest& r) { r.intervalUm = 0.01; },
                     +[](AtlasSliceRequest& r) { r.tiltLrDeg = std::nan(""); },
                     +[](AtlasSliceRequest& r) { r.tiltDvDeg = 61; },
                     +[](AtlasSliceRequest& r) { r.umPerPx = 1e-6; },
                     +[](AtlasSliceRequest& r) { r.firstUm = INFINITY; }}) {
        AtlasSliceRequest b;
        b.builtin = true;
        b.output = dir_;
        bad(b);
        auto out = runAtlasSlice(b);
        ASSERT_FALSE(out.ok());
        EXPECT_EQ(out.error().code, core::ErrorCode::InvalidArgument) << out.error().message;
        EXPECT_NE(out.error().message.find("is not a finite number in"), std::string::npos)
            << out.error().message;
    }
}

TEST_F(AtlasStackTest, MatchWindowOfIntMaxSearchesTheWholeStack) {
    AtlasSliceRequest rq;
    rq.builtin = true;
    rq.intervalUm = 800;
    rq.output = dir_ / "stack";
    ASSERT_TRUE(runAtlasSlice(rq).ok());
    sim::GeneratorOptions o;
    o.seed = 3;
    o.imageSize = {900, 660};
    auto gen = sim::generateSection(sim::builtinAtlasPlane(0.5), o);
    ASSERT_TRUE(gen.ok()) << gen.error().message;
    ASSERT_TRUE(core::writeImage(dir_ / "section.tif", gen->image).ok());
    AtlasMatchRequest m;
    m.stack = dir_ / "stack";
    m.image = dir_ / "section.tif";
    m.expectedIndex = 5;
    m.window = INT_MAX; // expectedIndex + window overflowed int
    m.output = dir_ / "match.json";
    auto r = runAtlasMatch(m);
    ASSERT_TRUE(r.ok()) << r.error().message;
    // 11 slices; the ends may hold no brain and are skipped.
    EXPECT_GE(r->at("candidates").size(), 9u) << "the whole stack searched";
}

TEST_F(AtlasStackTest, TheTemplatePlaneIsCutBesideEverySliceAndReadBack) {
    if (!fs::exists(kAtlasDir / "annotation_100.nrrd") ||
        !fs::exists(kAtlasDir / "average_template_100.nrrd"))
        GTEST_SKIP() << "no Allen annotation or template at " << kAtlasDir << " (SLST_SHARED_DIR)";
    AtlasSliceRequest rq = realVolumeRequest();
    rq.templateVolume = kAtlasDir / "average_template_100.nrrd";
    auto r = runAtlasSlice(rq);
    ASSERT_TRUE(r.ok()) << r.error().message;
    auto stack = readStack(dir_);
    ASSERT_TRUE(stack.ok()) << stack.error().message;
    ASSERT_EQ(stack->slices.size(), 26u);
    EXPECT_EQ(stack->source.at("template"), rq.templateVolume.string());
    auto templ = core::readNrrd(rq.templateVolume);
    ASSERT_TRUE(templ.ok());
    const double top = *std::max_element(templ->data.begin(), templ->data.end());
    for (int index : {2, 10, 20}) {
        EXPECT_EQ(stack->slices[size_t(index)].templateFile,
                  "template-0" + std::to_string(index / 10) + std::to_string(index % 10) + ".tif");
        auto plane = readStackTemplate(*stack, index);
        ASSERT_TRUE(plane.ok()) << plane.error().message;
        auto labels = readStackSlice(*stack, index);
        ASSERT_TRUE(labels.ok());
        ASSERT_EQ(plane->type(), CV_32F);
        ASSERT_EQ(plane->size(), labels->size());
        // Same voxel size and grid as the labels: an untilted plane is the template's plane.
        const int ap = (300 + 500 * index) / 100;
        for (const auto& [row, col] : {std::pair{40, 57}, std::pair{20, 30}, std::pair{60, 90}})
            EXPECT_NEAR(plane->at<float>(row, col), templ->at(ap, row, col) / top, 1e-5)
                << "slice " << index << " pixel " << row << ", " << col;
        // The template is bright in the brain and dark outside it.
        EXPECT_GT(cv::mean(*plane, *labels != 0)[0], 2 * cv::mean(*plane, *labels == 0)[0]);
    }
    // The registration gets the plane through the stack: written beside the labels in the
    // manifest, read back by the slice's entry.
    std::ifstream in(dir_ / "manifest.json");
    nlohmann::json manifest = nlohmann::json::parse(in);
    EXPECT_EQ(manifest["slices"][10]["template"], "template-010.tif");

    // Manifests come from outside: every bad template entry names itself.
    auto rewrite = [&](const nlohmann::json& value) {
        nlohmann::json m = manifest;
        m["slices"][3]["template"] = value;
        std::ofstream(dir_ / "manifest.json") << m.dump();
    };
    for (const nlohmann::json& bad :
         {nlohmann::json("../template-003.tif"), nlohmann::json("/etc/passwd"), nlohmann::json(5),
          nlohmann::json("")}) {
        rewrite(bad);
        auto s = readStack(dir_);
        ASSERT_FALSE(s.ok()) << bad.dump();
        EXPECT_EQ(s.error().code, core::ErrorCode::InvalidArgument);
        EXPECT_NE(s.error().message.find("slices[3].template"), std::string::npos)
            << s.error().message;
    }
    // A template file that is missing, a label image, or of another size.
    ASSERT_TRUE(core::writeImage(dir_ / "labels-as-template.tif", *readStackSlice(*stack, 3)).ok());
    ASSERT_TRUE(core::writeImage(dir_ / "small-template.tif", cv::Mat(8, 8, CV_32F, 0.5f)).ok());
    for (const auto& [file, code] :
         {std::pair{"nothing.tif", core::ErrorCode::NotFound},
          std::pair{"labels-as-template.tif", core::ErrorCode::InvalidArgument},
          std::pair{"small-template.tif", core::ErrorCode::InvalidArgument}}) {
        rewrite(file);
        auto s = readStack(dir_);
        ASSERT_TRUE(s.ok()) << s.error().message;
        auto plane = readStackTemplate(*s, 3);
        ASSERT_FALSE(plane.ok()) << file;
        EXPECT_EQ(plane.error().code, code) << plane.error().message;
        EXPECT_NE(plane.error().message.find("slices[3].template"), std::string::npos)
            << plane.error().message;
        EXPECT_NE(plane.error().message.find(file), std::string::npos) << plane.error().message;
    }
}

TEST_F(AtlasStackTest, StacksWithoutATemplateKeepWorking) {
    AtlasSliceRequest rq;
    rq.builtin = true;
    rq.intervalUm = 400;
    rq.output = dir_;
    ASSERT_TRUE(runAtlasSlice(rq).ok());
    auto stack = readStack(dir_);
    ASSERT_TRUE(stack.ok()) << stack.error().message;
    auto plane = readStackTemplate(*stack, 5);
    ASSERT_TRUE(plane.ok()) << plane.error().message;
    EXPECT_TRUE(plane->empty());
    EXPECT_EQ(readStackTemplate(*stack, 99).error().code, core::ErrorCode::OutOfRange);
    // The built-in atlas has no intensity volume to cut.
    rq.templateVolume = dir_ / "template.nrrd";
    auto r = runAtlasSlice(rq);
    ASSERT_FALSE(r.ok());
    EXPECT_NE(r.error().message.find("--template"), std::string::npos);
}
