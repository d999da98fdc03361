// Writes one generated section with its atlas slice and ground truth to files, for running
// `slicectl register` by hand or under /usr/bin/time (the large-image benchmark).
#include "bench_cases.hpp"
#include "elastix_runner.hpp"

#include "slicestation/pipeline/preprocess.hpp"

#include <opencv2/imgproc.hpp>

#include "slicestation/core/image_file.hpp"

#include <CLI/CLI.hpp>

#include <cmath>
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
    app.add_option("--plane-count", planeCount,
                   "Planes spread over the brain (48, as the benchmark)")
        ->check(CLI::Range(1, 400));
    app.add_option("--seed", seed, "Generator seed");
    app.add_flag("--tear", tear, "Tear the section");
    app.add_flag("--missing", missing, "Remove a chunk at the boundary");
    app.add_flag("--fragment", fragment, "Cut off and move a piece");
    app.add_flag("--brightfield", brightfield, "Brightfield stain");
    std::string family = "1", elastixDir, stain = "immuno", preview;
    app.add_option("--stain", stain, "Second family's stain: immuno, nissl or autofluorescence")
        ->check(CLI::IsMember({"immuno", "nissl", "autofluorescence"}));
    app.add_option("--preview", preview, "Also write an 8-bit PNG of the section, half size");
    bool fold = false;
    app.add_flag("--fold", fold, "Second family: fold a flap of the edge");
    app.add_option("--family", family, "1 (first), 2 (second, immuno stain) or template")
        ->check(CLI::IsMember({"1", "2", "template"}));
    app.add_option("--elastix-dir", elastixDir,
                   "Also write elastix's inputs here (fixed.mha, moving.mha, affine.txt, "
                   "bspline.txt, points.txt) for timing elastix as a process");
    app.add_option("--output-dir", out,
                   "Where to write section.tif, atlas.tif, points.csv, truth.csv");
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
    bench::BenchCase c;
    c.plane = plane;
    c.family = family == "1"   ? bench::Family::First
               : family == "2" ? bench::Family::Second
                               : bench::Family::Template;
    c.options.seed = c.optionsB.seed = seed;
    c.options.imageSize = c.optionsB.imageSize = {w, h};
    c.options.damage.tear = c.optionsB.damage.crack = tear;
    c.options.damage.missing = c.optionsB.damage.bite = missing;
    c.options.damage.fragment = c.optionsB.damage.fragment = fragment;
    c.options.stain = brightfield ? sim::Stain::Brightfield : sim::Stain::Fluorescence;
    c.optionsB.brightfield = brightfield;
    c.optionsB.stain = c.family == bench::Family::Template ? sim::StainB::Template
                       : stain == "nissl"                  ? sim::StainB::Nissl
                       : stain == "autofluorescence"       ? sim::StainB::Autofluorescence
                                                           : sim::StainB::Immuno;
    c.optionsB.damage.fold = fold;
    auto gen = bench::generate(c, *atlas);
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
    if (!preview.empty()) {
        cv::Mat small, preview8;
        cv::resize(gen->image, small, {}, 0.5, 0.5, cv::INTER_AREA);
        cv::normalize(small, preview8, 0, 255, cv::NORM_MINMAX, CV_8U);
        if (auto r = core::writeImage(preview, preview8); !r) {
            std::cerr << r.error().message << "\n";
            return 1;
        }
    }
    if (!elastixDir.empty()) {
        if (atlas->templatePlanes.empty()) {
            std::cerr << "--elastix-dir needs the Allen average template\n";
            return 1;
        }
        bench::ElastixInput in;
        auto grey = pipeline::toGreyFloat(gen->image);
        if (!grey) {
            std::cerr << grey.error().message << "\n";
            return 1;
        }
        in.fixed = *grey;
        const auto& A = gen->truth.affineAtlasFromImage;
        in.fixedSpacingUm =
            atlas->umPerPx * std::sqrt(std::abs(A(0, 0) * A(1, 1) - A(0, 1) * A(1, 0)));
        in.moving = bench::templatePlane100(*atlas, plane);
        in.movingSpacingUm = 100;
        in.movingOriginUm = 37.5;
        for (const auto& l : gen->truth.landmarks)
            in.points.push_back(l.image);
        bench::writeElastixInputs(in, elastixDir);
    }
    std::cout << "wrote " << (dir / "section.tif").string() << " (" << w << "x" << h << "), atlas "
              << atlas->name << " plane " << plane << "\n";
    return 0;
}
