// slicectl export against the station's HTTP API, end to end: a simulated run over the built-in
// atlas (a clean section and the torn one), then the QuPath export of the run written as one
// GeoJSON per section, the damage as its own class, and the QuickNII export refused (the built-in
// atlas is not CCFv3), with slicectl's exit codes.
#include "station_fixture.hpp"

#include <gtest/gtest.h>

#include <sys/wait.h>

#include <cstdio>
#include <filesystem>
#include <fstream>

using namespace slicestation;
using namespace slicestation::daemon;
using namespace slicestation::testing_station;
namespace fs = std::filesystem;

namespace {

struct Ran {
    int code = -1;
    std::string out;
};

Ran slicectl(const std::string& args) {
    const std::string cmd = std::string(SLICECTL_PATH) + " " + args + " 2>&1";
    Ran r;
    FILE* p = ::popen(cmd.c_str(), "r");
    char buf[4096];
    while (p && std::fgets(buf, sizeof buf, p))
        r.out += buf;
    const int st = p ? ::pclose(p) : -1;
    r.code = WIFEXITED(st) ? WEXITSTATUS(st) : -1;
    return r;
}

TEST_F(StationTest, SlicectlExportsARunForQuPathAndRefusesQuickNiiForTheBuiltinAtlas) {
    build();
    auto id = rig_.station->submitPlan(planFor({0, 2}), "plan");
    ASSERT_TRUE(id) << id.error().message;
    rig_.station->start();
    waitRun(*id, RunState::Finished);
    auto api = HttpApi::start(*rig_.station, "127.0.0.1", 0, kToken);
    ASSERT_TRUE(api) << api.error().message;
    rig_.api = std::move(*api);
    const std::string url = " --url http://127.0.0.1:" + std::to_string(rig_.api->port());
    const std::string run = std::to_string(*id);

    // Every section's result keeps its mapping and atlas slice.
    auto secs = rig_.station->journal().sections(*id);
    ASSERT_TRUE(secs);
    for (const auto& s : *secs) {
        auto regs = rig_.station->journal().registrations(s.id);
        ASSERT_EQ(regs->size(), 1u);
        const auto& doc = regs->front().result;
        EXPECT_EQ(doc["atlas"]["stack"]["index"], regs->front().atlasSlice);
        EXPECT_FALSE(doc["atlas"]["stack"]["ccf"].get<bool>());
        const fs::path result = rig_.dir / regs->front().resultPath;
        EXPECT_TRUE(fs::exists(result.parent_path() / doc["mapping"]["field"].get<std::string>()));
    }

    const fs::path out = rig_.dir / "qupath-export";
    Ran r = slicectl("export " + run + " --format qupath --output " + out.string() + url);
    ASSERT_EQ(r.code, 0) << r.out;
    EXPECT_NE(r.out.find("wrote 2 GeoJSON files"), std::string::npos) << r.out;
    std::ifstream idx(out / "run.json");
    const nlohmann::json index = nlohmann::json::parse(idx);
    ASSERT_EQ(index["sections"].size(), 2u);
    int damageFeatures = 0;
    for (const auto& s : index["sections"]) {
        std::ifstream in(out / s["file"].get<std::string>());
        ASSERT_TRUE(in) << s.dump();
        const nlohmann::json fc = nlohmann::json::parse(in);
        ASSERT_EQ(fc["type"], "FeatureCollection");
        int regions = 0, damage = 0;
        for (const auto& f : fc["features"]) {
            const auto& props = f["properties"];
            if (props["classification"]["name"] == "Damage") {
                ++damage;
                continue;
            }
            ++regions;
            EXPECT_TRUE(props["hemisphere"] == "left" || props["hemisphere"] == "right");
            EXPECT_FALSE(props["region_name"].get<std::string>().empty());
        }
        EXPECT_GT(regions, 10) << s["section"];
        if (s["section"] == "s3") {
            EXPECT_GT(damage, 0) << "the torn section's damage is exported";
        }
        damageFeatures += damage;
    }
    EXPECT_GT(damageFeatures, 0);

    // QuickNII needs CCFv3 coordinates: input error (2) naming why.
    r = slicectl("export " + run + " --format quicknii" + url);
    EXPECT_EQ(r.code, 2) << r.out;
    EXPECT_NE(r.out.find("CCF"), std::string::npos) << r.out;
    // The csv and json summaries are unchanged.
    r = slicectl("export " + run + " --format csv" + url);
    EXPECT_EQ(r.code, 0) << r.out;
    // qupath without a directory: usage (1); no such run: input (2); no daemon: 3.
    EXPECT_EQ(slicectl("export " + run + " --format qupath" + url).code, 1);
    EXPECT_EQ(slicectl("export 999 --format qupath --output " + out.string() + url).code, 2);
    EXPECT_EQ(slicectl("export " + run + " --format qupath --output " + out.string() +
                       " --url http://127.0.0.1:1")
                  .code,
              3);
}

} // namespace
