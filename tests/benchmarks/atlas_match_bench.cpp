// Atlas matching benchmark: sections generated from known planes of the 50 um annotation
// (random positions between the stack's slices, half of them tilted), matched against a 100 um
// stack without hints. Prints the position error in micrometres and the time per section.
// Without ../shared it uses the built-in atlas.
#include "slicestation/core/image_file.hpp"
#include "slicestation/core/nrrd.hpp"
#include "slicestation/core/ontology.hpp"
#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/pipeline/atlas_matching.hpp"
#include "slicestation/pipeline/atlas_slicing.hpp"
#include "slicestation/sim/builtin_atlas.hpp"
#include "slicestation/sim/section_generator.hpp"

#include <CLI/CLI.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <random>

using namespace slicestation;
namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;

namespace {

double msSince(Clock::time_point t) {
    return std::chrono::duration<double, std::milli>(Clock::now() - t).count();
}

} // namespace

int main(int argc, char** argv) {
    CLI::App app{"Atlas matching benchmark"};
    int cases = 40;
    double intervalUm = 100, maxTiltDeg = 3;
    std::uint64_t seed = 11;
    std::string size = "1200x880";
    std::string shared = SLST_SHARED_DIR;
    bool knownScale = true, verbose = false;
    app.add_flag("--verbose", verbose, "Print the candidates of every case, not only the misses");
    int workPx = 320;
    std::string dump;
    int onlyCase = -1;
    app.add_option("--dump", dump, "Write each case's section image (caseNN.png) to this folder");
    app.add_option("--only-case", onlyCase, "Run only this case (the sequence stays the same)");
    app.add_option("--work-px", workPx, "Matching resolution: px across the largest brain");
    app.add_option("--cases", cases, "Generated sections")->check(CLI::PositiveNumber);
    app.add_option("--interval-um", intervalUm, "Stack interval");
    app.add_option("--max-tilt-deg", maxTiltDeg, "Tilt of half the cases, uniform in +/-");
    app.add_option("--seed", seed, "Random seed");
    app.add_option("--size", size, "Section image size WxH");
    app.add_option("--shared", shared, "Shared data directory");
    app.add_flag("--known-scale,!--unknown-scale", knownScale,
                 "Give the section's pixel size to the matcher (default) or not");
    CLI11_PARSE(app, argc, argv);
    int w = 0, h = 0;
    if (std::sscanf(size.c_str(), "%dx%d", &w, &h) != 2) {
        std::fprintf(stderr, "--size must be WxH\n");
        return 2;
    }

    // The atlas: the 50 um annotation collapsed to the major regions, or the built-in brain.
    const fs::path dir = fs::path(shared) / "atlas" / "allen-ccf-2017";
    const bool real = fs::exists(dir / "annotation_50.nrrd");
    core::Volume volume;
    core::Ontology ontology;
    if (real) {
        auto v = core::readNrrd(dir / "annotation_50.nrrd");
        auto o = core::readOntologyCsv(dir / "structure_tree_safe_2017.csv");
        if (!v || !o) {
            std::fprintf(stderr, "cannot read the Allen files in %s\n", dir.c_str());
            return 1;
        }
        volume = std::move(*v);
        ontology = std::move(*o);
    }
    const double stackUmPerPx = 50, sectionAtlasUmPerPx = 25;
    const double lengthUm =
        real ? pipeline::volumeExtentUm(volume, pipeline::VolumeAxes::Allen)[0] : 8000.0;
    auto collapse = [&](const cv::Mat& l) {
        return real ? pipeline::collapseLabels(l, ontology, pipeline::majorRegionIds(),
                                               pipeline::kOtherRegionId)
                    : l;
    };
    auto cut = [&](double pos, double ta, double tb, double um) -> cv::Mat {
        if (!real)
            return sim::builtinAtlasPlane(pos / lengthUm);
        auto g = pipeline::planeGeometry(volume, pipeline::VolumeAxes::Allen,
                                         {pipeline::PlaneOrientation::Coronal, pos, ta, tb, um});
        auto s = g ? pipeline::sampleLabels(volume, pipeline::VolumeAxes::Allen, *g)
                   : core::Result<cv::Mat>(g.error());
        return s ? collapse(*s) : cv::Mat();
    };

    const auto t0 = Clock::now();
    std::vector<cv::Mat> stackLabels;
    std::vector<double> positions;
    for (double p = 0; p <= lengthUm + 1e-6; p += intervalUm) {
        stackLabels.push_back(cut(p, 0, 0, real ? stackUmPerPx : 25));
        positions.push_back(p);
    }
    const double stackUm = real ? stackUmPerPx : 25;
    const double workUm = pipeline::matchWorkUmPerPx(stackLabels, stackUm, workPx);
    std::vector<pipeline::SliceFeatures> features;
    for (size_t i = 0; i < stackLabels.size(); ++i)
        features.push_back(pipeline::sliceFeatures(stackLabels[i], stackUm, positions[i], workUm));
    std::printf("atlas %s, stack of %zu slices every %.0f um, features in %.0f ms (%.1f um/px)\n",
                real ? "allen-ccf-50um (major regions)" : "builtin", features.size(), intervalUm,
                msSince(t0), workUm);

    std::mt19937_64 rng(seed);
    std::uniform_real_distribution<double> posDist(0.08 * lengthUm, 0.92 * lengthUm);
    std::uniform_real_distribution<double> tiltDist(-maxTiltDeg, maxTiltDeg);
    int within = 0, done = 0, failed = 0;
    std::vector<double> errors, times, tiltErrors;
    std::printf("%5s %9s %6s %6s %9s %7s %7s %8s\n", "case", "true_um", "tiltLR", "tiltDV",
                "found_um", "err_um", "ms", "tilt_est");
    for (int c = 0; c < cases; ++c) {
        const double pos = posDist(rng);
        const bool tilted = c % 2 == 1;
        const double ta = tilted ? tiltDist(rng) : 0, tb = tilted ? tiltDist(rng) : 0;
        const cv::Mat plane = cut(pos, ta, tb, real ? sectionAtlasUmPerPx : 25);
        sim::GeneratorOptions go;
        go.seed = seed * 1000 + std::uint64_t(c);
        go.imageSize = {w, h};
        if (onlyCase >= 0 && c != onlyCase)
            continue;
        auto gen = sim::generateSection(plane, go);
        if (!gen) {
            std::printf("%5d generator: %s\n", c, gen.error().message.c_str());
            continue;
        }
        const double atlasUm = real ? sectionAtlasUmPerPx : 25;
        const double imageUm =
            knownScale
                ? std::sqrt(std::abs(cv::determinant(cv::Matx22d(
                      gen->truth.affineAtlasFromImage(0, 0), gen->truth.affineAtlasFromImage(0, 1),
                      gen->truth.affineAtlasFromImage(1, 0),
                      gen->truth.affineAtlasFromImage(1, 1))))) *
                      atlasUm
                : 0.0;
        if (!dump.empty()) {
            cv::Mat view;
            cv::normalize(gen->image, view, 0, 255, cv::NORM_MINMAX, CV_8U);
            char name[32];
            std::snprintf(name, sizeof name, "case%02d.png", c);
            if (auto wr = core::writeImage(fs::path(dump) / name, view); !wr)
                std::fprintf(stderr, "%s\n", wr.error().message.c_str());
        }
        const auto t = Clock::now();
        auto sec = pipeline::sectionFeatures(gen->image, imageUm, workUm);
        const double prepMs = msSince(t);
        auto m = sec ? pipeline::matchSection(*sec, features)
                     : core::Result<pipeline::SectionMatch>(sec.error());
        const double ms = msSince(t);
        ++done;
        if (!m) {
            ++failed;
            std::printf("%5d %9.0f failed: %s\n", c, pos, m.error().message.c_str());
            continue;
        }
        const double err = std::abs(m->positionUm - pos);
        errors.push_back(err);
        times.push_back(ms);
        within += err <= intervalUm;
        if (m->tiltEstimated && tilted)
            tiltErrors.push_back(std::hypot(m->tiltColumnsDeg - ta, m->tiltRowsDeg - tb));
        std::printf("%5d %9.0f %6.1f %6.1f %9.0f %7.0f %7.0f %4.1f/%4.1f  prepare %.0f", c, pos, ta,
                    tb, m->positionUm, err, ms, m->tiltColumnsDeg, m->tiltRowsDeg, prepMs);
        for (const auto& [step, v] : m->timingsMs)
            std::printf(" %s %.0f", step.c_str(), v);
        std::printf("\n");
        if (err > intervalUm || verbose) {
            // What the matcher weighed: the best candidates and the slices around the truth.
            std::printf("      candidates (index score overlap edges regions):");
            for (size_t k = 0; k < m->candidates.size(); ++k) {
                const auto& cd = m->candidates[k];
                const bool nearTruth = std::abs(positions[size_t(cd.index)] - pos) <= intervalUm;
                if (k < 4 || nearTruth)
                    std::printf(" %s%d %.3f %.2f %.3f %.3f", nearTruth ? "*" : "", cd.index,
                                cd.score, cd.overlap, cd.edgeAgreement, cd.regionAgreement);
            }
            std::printf("\n");
        }
    }
    auto median = [](std::vector<double> v) {
        if (v.empty())
            return 0.0;
        std::nth_element(v.begin(), v.begin() + long(v.size() / 2), v.end());
        return v[v.size() / 2];
    };
    auto mean = [](const std::vector<double>& v) {
        double s = 0;
        for (double x : v)
            s += x;
        return v.empty() ? 0.0 : s / double(v.size());
    };
    std::printf("\nsections %d, failed %d, within one slice (<= %.0f um): %d (%.1f%%)\n", done,
                failed, intervalUm, within, done ? 100.0 * within / done : 0.0);
    std::printf("position error um: median %.0f, mean %.0f, max %.0f\n", median(errors),
                mean(errors),
                errors.empty() ? 0.0 : *std::max_element(errors.begin(), errors.end()));
    std::printf(
        "time per section ms (prepare + match, %zu slices): median %.0f, mean %.0f, max %.0f\n",
        features.size(), median(times), mean(times),
        times.empty() ? 0.0 : *std::max_element(times.begin(), times.end()));
    if (!tiltErrors.empty())
        std::printf("tilt error deg (tilted cases): median %.1f, mean %.1f\n", median(tiltErrors),
                    mean(tiltErrors));
    return failed == done ? 1 : 0;
}
