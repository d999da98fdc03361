// slicectl count, end to end through the real binary: a generated section with labelled cells at
// known positions, registered, then counted per region with the Allen ontology.
#include "../../common/run_command.hpp"
#include "slicestation/core/csv.hpp"
#include "slicestation/core/image_file.hpp"
#include "slicestation/core/ontology.hpp"
#include "slicestation/daemon/station/cell_counts.hpp"
#include "slicestation/sim/builtin_atlas.hpp"
#include "slicestation/sim/section_generator.hpp"

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <sstream>
#include <unistd.h>

using namespace slicestation;
namespace fs = std::filesystem;

namespace {

using testing_cli::CommandResult;
using testing_cli::slicectl;

std::vector<core::CsvRecord> readCsv(const fs::path& p) {
    std::ifstream in(p);
    std::ostringstream s;
    s << in.rdbuf();
    auto r = core::parseCsv(s.str(), p.string());
    EXPECT_TRUE(r.ok());
    return r.ok() ? *r : std::vector<core::CsvRecord>{};
}

const fs::path kOntology =
    fs::path(SLST_SHARED_DIR) / "atlas" / "allen-ccf-2017" / "structure_tree_safe_2017.csv";

class SlicectlCount : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        dir_ = fs::temp_directory_path() / ("slst_count_" + std::to_string(::getpid()));
        fs::create_directories(dir_);
        const cv::Mat atlas = sim::builtinAtlasPlane(0.5);
        sim::GeneratorOptions o;
        o.seed = 7;
        o.imageSize = {1200, 880};
        o.cells.enabled = true;
        o.cells.diameterPx = 6;
        o.cells.meanPerMpx = 1500;
        auto gen = sim::generateSection(atlas, o);
        ASSERT_TRUE(gen.ok()) << gen.error().message;
        for (const auto& c : gen->cells)
            if (c.counted && c.atlasId > 0)
                ++truth_[c.atlasId], ++total_;
        ASSERT_TRUE(core::writeImage(dir_ / "atlas.tif", atlas).ok());
        ASSERT_TRUE(core::writeImage(dir_ / "section.tif", gen->image).ok());
        const CommandResult r = slicectl("register --atlas " + p("atlas.tif") + " --image " +
                                         p("section.tif") + " --output " + p("result.json"));
        ASSERT_EQ(r.exitCode, 0) << r.output;
    }
    static void TearDownTestSuite() { fs::remove_all(dir_); }
    static std::string p(const std::string& name) { return (dir_ / name).string(); }

    static fs::path dir_;
    static std::map<std::int32_t, int> truth_;
    static int total_;
};
fs::path SlicectlCount::dir_;
std::map<std::int32_t, int> SlicectlCount::truth_;
int SlicectlCount::total_ = 0;

} // namespace

TEST_F(SlicectlCount, WritesCountsAndCellsCloseToTheTruth) {
    // 15 um cells at 2.5 um/px: the generator's 6 px.
    const CommandResult r =
        slicectl("count --result " + p("result.json") + " --image " + p("section.tif") +
                 " --image-um-per-px 2.5 --output " + p("counts.csv") + " --cells " +
                 p("cells.csv") + " --ontology " + kOntology.string());
    ASSERT_EQ(r.exitCode, 0) << r.output;
    const auto counts = readCsv(p("counts.csv"));
    ASSERT_GT(counts.size(), 3u);
    EXPECT_EQ(counts[0].fields,
              (std::vector<std::string>{"id", "acronym", "name", "parent_id", "depth", "count",
                                        "area_mm2", "density_per_mm2"}));
    std::map<std::string, std::pair<long, double>> byId;
    for (size_t i = 1; i < counts.size(); ++i)
        byId[counts[i].fields[0]] = {std::stol(counts[i].fields[5]),
                                     std::stod(counts[i].fields[6])};
    ASSERT_TRUE(byId.count("997")) << "no root row: the counts were not rolled up";
    std::cout << "counted " << byId["997"].first << " cells for " << total_ << " true\n";
    // The whole brain: every counted cell, near the truth (detector and registration). Measured:
    // 611 counted for 550 true (+11%; 527, -4%, before the area split of touching cells: on this
    // built-in-atlas section the split also multiplies detections the LoG took in stain texture,
    // docs/cells.md); slst_bench_cells carries the accuracy figures.
    EXPECT_NEAR(double(byId["997"].first), double(total_), 0.20 * total_);
    // Area: the section's tissue at 2.5 um/px, a few mm^2 (1200 x 880 px = 6.6 mm^2 in all).
    EXPECT_GT(byId["997"].second, 1.5);
    EXPECT_LT(byId["997"].second, 6.6);
    // The largest region of the truth (measured: isocortex 180 for 159; 155 before the split).
    auto largest = std::max_element(truth_.begin(), truth_.end(),
                                    [](auto& a, auto& b) { return a.second < b.second; });
    ASSERT_TRUE(byId.count(std::to_string(largest->first)));
    EXPECT_NEAR(double(byId[std::to_string(largest->first)].first), double(largest->second),
                0.25 * largest->second)
        << "largest region " << largest->first;
    std::cout << "largest region " << largest->first << ": "
              << byId[std::to_string(largest->first)].first << " for " << largest->second << "\n";

    const auto cells = readCsv(p("cells.csv"));
    ASSERT_GT(cells.size(), 100u);
    EXPECT_EQ(cells[0].fields[0], "x");
    EXPECT_EQ(cells[0].fields[2], "ccf_x_um");
    EXPECT_EQ(cells[0].fields[5], "id");
    EXPECT_EQ(cells[0].fields[6], "acronym");
    long counted = 0;
    for (size_t i = 1; i < cells.size(); ++i) {
        EXPECT_EQ(cells[i].fields[2], ""); // not a stack slice: no CCF
        if (cells[i].fields[5] != "0" && cells[i].fields[9] == "0")
            counted += std::stol(cells[i].fields[10]);
    }
    EXPECT_EQ(counted, byId["997"].first);
}

TEST_F(SlicectlCount, NeedsThePixelSize) {
    CommandResult r = slicectl("count --result " + p("result.json") + " --output " + p("c2.csv") +
                               " --image " + p("section.tif"));
    EXPECT_EQ(r.exitCode, 2) << r.output;
    EXPECT_NE(r.output.find("--image-um-per-px"), std::string::npos) << r.output;
    EXPECT_FALSE(fs::exists(p("c2.csv")));
    r = slicectl("count --result " + p("section.tif") + " --image-um-per-px 2.5 --output " +
                 p("c4.csv"));
    EXPECT_EQ(r.exitCode, 2) << r.output;
}

TEST_F(SlicectlCount, ReadsTheSavedMappingAndRegistersAgainOnlyWithoutOne) {
    auto count = [&](const std::string& result, const std::string& out) {
        return slicectl("count --result " + p(result) + " --image-um-per-px 2.5 --ontology " +
                        kOntology.string() + " --output " + p(out + ".csv") + " --cells " +
                        p(out + "-cells.csv"));
    };
    auto text = [&](const std::string& name) {
        std::ifstream in(p(name));
        std::ostringstream s;
        s << in.rdbuf();
        return s.str();
    };
    std::ifstream in(p("result.json"));
    const auto doc = nlohmann::json::parse(in);
    ASSERT_TRUE(doc.contains("mapping"));

    // The saved mapping (affine + field TIFF): no registration, no note.
    CommandResult r = count("result.json", "saved");
    ASSERT_EQ(r.exitCode, 0) << r.output;
    EXPECT_EQ(r.output.find("note:"), std::string::npos) << r.output;
    EXPECT_NE(r.output.find("mapping saved"), std::string::npos) << r.output;

    // A result without it (written before the mapping was kept): registered again, with a note
    // on stderr, and the counts and every cell are those of the saved mapping.
    auto old = doc;
    old.erase("mapping");
    std::ofstream(p("old.json")) << old.dump();
    r = count("old.json", "again");
    ASSERT_EQ(r.exitCode, 0) << r.output;
    EXPECT_NE(r.output.find("registering the section again"), std::string::npos) << r.output;
    EXPECT_EQ(text("saved.csv"), text("again.csv"));
    EXPECT_EQ(text("saved-cells.csv"), text("again-cells.csv"));
    EXPECT_GT(readCsv(p("saved.csv")).size(), 3u);

    // The saved mapping is what is read: its affine moved 5 atlas px moves every cell's atlas x.
    auto moved = doc;
    moved["mapping"]["affine_atlas_from_working"][0][2] =
        moved["mapping"]["affine_atlas_from_working"][0][2].get<double>() + 5;
    std::ofstream(p("moved-saved.json")) << moved.dump();
    r = count("moved-saved.json", "moved");
    ASSERT_EQ(r.exitCode, 0) << r.output;
    const auto a = readCsv(p("saved-cells.csv")), b = readCsv(p("moved-cells.csv"));
    ASSERT_EQ(a.size(), b.size());
    ASSERT_GT(a.size(), 10u);
    EXPECT_NEAR(std::stod(b[1].fields[7]) - std::stod(a[1].fields[7]), 5.0, 1e-3);

    // Registering again must give the stored affine: a moved one is refused, nothing written.
    old["affine_atlas_from_image"][0][2] = old["affine_atlas_from_image"][0][2].get<double>() + 5;
    std::ofstream(p("moved.json")) << old.dump();
    r = count("moved.json", "c3");
    EXPECT_EQ(r.exitCode, 2) << r.output;
    EXPECT_NE(r.output.find("atlas px away"), std::string::npos) << r.output;
    EXPECT_FALSE(fs::exists(p("c3.csv")));

    // A saved mapping whose field file is gone is an error (not a silent re-registration).
    auto lost = doc;
    lost["mapping"]["field"] = "no-such-field.tif";
    std::ofstream(p("lost.json")) << lost.dump();
    r = count("lost.json", "c5");
    EXPECT_NE(r.exitCode, 0) << r.output;
    EXPECT_NE(r.output.find("no-such-field.tif"), std::string::npos) << r.output;
    EXPECT_FALSE(fs::exists(p("c5.csv")));
}

TEST_F(SlicectlCount, RunTotalsSumSectionTables) {
    const std::string head = "id,acronym,name,parent_id,depth,count,area_mm2,density_per_mm2\n";
    std::ofstream(p("a.csv")) << head
                              << "997,root,root,,0,10,2,5\n8,grey,\"Grey, basic\",997,1,4,1,4\n";
    std::ofstream(p("b.csv")) << head << "997,root,root,,0,6,1,6\n";
    auto sum = daemon::sumCountsCsv({p("a.csv"), p("b.csv")});
    ASSERT_TRUE(sum.ok()) << sum.error().message;
    auto recs = core::parseCsv(*sum, "sum");
    ASSERT_TRUE(recs.ok());
    ASSERT_EQ(recs->size(), 3u);
    EXPECT_EQ((*recs)[1].fields[0], "8");
    EXPECT_EQ((*recs)[1].fields[2], "Grey, basic");
    EXPECT_EQ((*recs)[2].fields[5], "16");
    EXPECT_EQ((*recs)[2].fields[6], "3");
    EXPECT_EQ((*recs)[2].fields[7], "5.33333");
    std::ofstream(p("bad.csv")) << "x,y\n1,2\n";
    EXPECT_FALSE(daemon::sumCountsCsv({p("a.csv"), p("bad.csv")}).ok());
}
