// slicectl: the station's command-line tool.
#include "slicestation/daemon/demo_command.hpp"
#include "slicestation/daemon/register_command.hpp"

#include <CLI/CLI.hpp>

#include <iostream>

namespace {

using namespace slicestation;

int fail(const char* command, const core::Error& e) {
    std::cerr << "slicectl " << command << ": error: " << e.message << "\n";
    return e.code == core::ErrorCode::Internal ? 1 : 2;
}

} // namespace

int main(int argc, char** argv) {
    CLI::App app{"slicestation: register mouse-brain sections to an annotated atlas"};
    app.require_subcommand(1);

    daemon::RegisterRequest rq;
    std::string points, overlay, warped;
    auto* reg = app.add_subcommand("register", "Register one section image to one atlas slice");
    reg->add_option("--atlas", rq.atlas, "Atlas label image (ids or colour-coded RGB)")->required();
    reg->add_option("--image", rq.image, "Section image (PNG or TIFF)")->required();
    reg->add_option("--points", points, "CSV with header x,y: section pixels to map");
    reg->add_option("--output", rq.output, "Result JSON")->required();
    reg->add_option("--overlay", overlay, "Overlay PNG: section with atlas outlines");
    reg->add_option("--warped-labels", warped, "Atlas labels in the section frame (TIFF)");
    reg->add_option("--image-um-per-px", rq.imageUmPerPx, "Section pixel size (prior on scale)")
        ->check(CLI::PositiveNumber);
    reg->add_option("--atlas-um-per-px", rq.atlasUmPerPx, "Atlas pixel size (prior on scale)")
        ->check(CLI::PositiveNumber);
    reg->add_option("--working-size", rq.workingMaxSide, "Longer side of the working image")
        ->check(CLI::Range(128, 8192));

    daemon::DemoRequest demo;
    auto* dem = app.add_subcommand(
        "demo", "Generate a section from the built-in atlas, register it, check it");
    dem->add_option("--output-dir", demo.outputDir, "Where to write the files");
    dem->add_option("--seed", demo.seed, "Generator seed");
    dem->add_flag("--damaged", demo.damaged, "Tear the generated section");

    try {
        app.parse(argc, argv);
    } catch (const CLI::ParseError& e) {
        return app.exit(e);
    }
    if (*reg) {
        if (!points.empty()) rq.points = points;
        if (!overlay.empty()) rq.overlay = overlay;
        if (!warped.empty()) rq.warpedLabels = warped;
        auto r = daemon::runRegister(rq);
        if (!r) return fail("register", r.error());
        std::cout << "registered " << rq.image.string() << " -> " << rq.output.string()
                  << " (tissue overlap " << (*r)["quality"]["tissue_overlap"].get<double>()
                  << ", " << (*r)["quality"]["correspondences"].get<int>()
                  << " correspondences, " << (*r)["timings_ms"]["total"].get<double>() << " ms)\n";
        return 0;
    }
    if (*dem) {
        auto r = daemon::runDemo(demo);
        if (!r) return fail("demo", r.error());
        std::cout << r->dump(2) << "\n";
        return 0;
    }
    return 0;
}
