// Writes one generated section with its atlas slice and ground truth to files, for running
// `slicectl register` by hand or under /usr/bin/time (the large-image benchmark).
#include "bench_cases.hpp"

#include "slicestation/core/image_file.hpp"

#include <CLI/CLI.hpp>

#include <cstdio>
#include <fstream>
#include <iostream>

using namespace slicestation;

int main(int argc, char** argv) {
    CLI::App app{"write a generated section, its atlas slice and landmarks"};
    std::string shared = SLST_SHARED_DIR, sizeText = "1500x1100", out = ".";
    int plane = 10, planeCount = 48;
    std::uint64_t seed = 1;
    bool tear = false, missing = false, fragment = false, brightfield = false;
    app.add_option("--shared", shared, "Path of ../shared (real atlas)");
    app.add_option("--size", sizeText, "Image size WxH");
    app.add_option("--plane", plane, "Atlas plane, 0 = front")->check(CLI::NonNegativeNumber);
    app.add_option("--plane-count", planeCount, "Planes spread over the brain (48, as the benchmark)")
        ->check(CLI::Range(1, 400));
    app.add_option("--seed", seed, "Generator seed");
    app.add_flag("--tear", tear, "Tear the section");
    app.add_flag("--missing", missing, "Remove a chunk at the boundary");
    app.add_flag("--fragment", fragment, "Cut off and move a piece");
    app.add_flag("--brightfield", brightfield, "Brightfield stain");
    app.add_option("--output-dir", out, "Where to write section.tif, atlas.tif, points.csv, truth.csv");
    CLI11_PARSE(app, argc, argv);
    int w = 0, h = 0;
    if (std::sscanf(sizeText.c_str(), "%dx%d", &w, &h) != 2) {
        std::cerr << "--size must be WxH\n";
        return 2;
    }
    if (plane >= planeCount) {
        std::cerr << "--plane must be below --plane-count\n";
        return 2;
    }
    auto atlas = bench::loadAtlasPlanes(shared, planeCount);
    if (!atlas) {
        std::cerr << atlas.error().message << "\n";
        return 1;
    }
    sim::GeneratorOptions o;
    o.seed = seed;
    o.imageSize = {w, h};
    o.damage.tear = tear;
    o.damage.missing = missing;
    o.damage.fragment = fragment;
    o.stain = brightfield ? sim::Stain::Brightfield : sim::Stain::Fluorescence;
    auto gen = sim::generateSection(atlas->planes[plane], o);
    if (!gen) {
        std::cerr << gen.error().message << "\n";
        return 1;
    }
    const std::filesystem::path dir(out);
    std::filesystem::create_directories(dir);
    if (auto r = core::writeImage(dir / "section.tif", gen->image); !r) {
        std::cerr << r.error().message << "\n";
        return 1;
    }
    if (auto r = core::writeImage(dir / "atlas.tif", atlas->planes[plane]); !r) {
        std::cerr << r.error().message << "\n";
        return 1;
    }
    std::ofstream pts(dir / "points.csv"), truth(dir / "truth.csv");
    pts << "x,y\n";
    truth << "x,y,atlas_x,atlas_y\n";
    for (const auto& l : gen->truth.landmarks) {
        pts << l.image.x << ',' << l.image.y << '\n';
        truth << l.image.x << ',' << l.image.y << ',' << l.atlas.x << ',' << l.atlas.y << '\n';
    }
    std::cout << "wrote " << (dir / "section.tif").string() << " (" << w << "x" << h << "), atlas "
              << atlas->name << " plane " << plane << "\n";
    return 0;
}
