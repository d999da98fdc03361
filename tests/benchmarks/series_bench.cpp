// Series benchmark (issue 19): sections of one brain matched live, one at a time, with the series
// model (pipeline/series_matching.hpp) against a coronal stack of the 50 um annotation.
//  - generated: a series cut from the 50 um annotation at a known tilt and spacing, with a skipped
//    section and a swapped pair; ground truth: every position, the slots, the tilt;
//  - gerbi: ../shared/sections/abba-gerbi-series (25 RGB fluorescence sections), compared with
//    the curated ABBA positions of sections.csv and ABBA's tilt;
//  - mouse: ../shared/sections/abba-mouse-series (20 sections), order and evenness only.
// Prints a table per section and the summary lines the targets are read from.
#include "../common/gerbi_series.hpp"
#include "../common/major_region_stack.hpp"
#include "slicestation/core/image_file.hpp"
#include "slicestation/core/nrrd.hpp"
#include "slicestation/core/ontology.hpp"
#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/pipeline/atlas_matching.hpp"
#include "slicestation/pipeline/atlas_slicing.hpp"
#include "slicestation/pipeline/series_matching.hpp"
#include "slicestation/sim/section_generator.hpp"

#include <CLI/CLI.hpp>
#include <opencv2/imgproc.hpp>

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

constexpr double kPi = 3.14159265358979323846;

double msSince(Clock::time_point t) {
    return std::chrono::duration<double, std::milli>(Clock::now() - t).count();
}

double percentile(std::vector<double> v, double q) {
    if (v.empty())
        return 0;
    std::sort(v.begin(), v.end());
    const double x = q * double(v.size() - 1);
    const size_t i = size_t(x);
    const double f = x - double(i);
    return i + 1 < v.size() ? v[i] * (1 - f) + v[i + 1] * f : v[i];
}

int inversions(const std::vector<double>& p) {
    int n = 0;
    for (size_t i = 1; i < p.size(); ++i)
        n += p[i] <= p[i - 1];
    return n;
}

/// Spearman's rank correlation of positions with the section order.
double spearman(const std::vector<double>& p) {
    const size_t n = p.size();
    std::vector<size_t> idx(n);
    for (size_t i = 0; i < n; ++i)
        idx[i] = i;
    std::sort(idx.begin(), idx.end(), [&](size_t a, size_t b) { return p[a] < p[b]; });
    std::vector<double> rank(n);
    for (size_t r = 0; r < n; ++r)
        rank[idx[r]] = double(r);
    double d2 = 0;
    for (size_t i = 0; i < n; ++i)
        d2 += (rank[i] - double(i)) * (rank[i] - double(i));
    const double nn = double(n);
    return n > 1 ? 1 - 6 * d2 / (nn * (nn * nn - 1)) : 1;
}

/// The generated series' cutting sequence: 22 planned slots, slot 8 lost, slots 14 and 15
/// mounted swapped (arrival index 13 and 14 after the skip).
std::vector<int> skipAndSwapSlots() {
    std::vector<int> slots;
    for (int s = 0; s < 22; ++s)
        if (s != 8)
            slots.push_back(s);
    std::swap(slots[13], slots[14]);
    return slots;
}

/// Whether the fit found what skipAndSwapSlots planted: the skip before arrival 8, and arrivals
/// 13 and 14 swapped.
struct PlantedFound {
    bool skip = false;
    bool swap = false;
};
PlantedFound plantedFound(const std::vector<pipeline::SeriesSectionFit>& f) {
    return {f[8].anomaly == pipeline::SeriesAnomaly::Skipped,
            f[13].anomaly == pipeline::SeriesAnomaly::Swapped &&
                f[14].anomaly == pipeline::SeriesAnomaly::Swapped};
}

struct Stack {
    std::vector<pipeline::SliceFeatures> features;
    double workUm = 0;
};

struct RunResult {
    std::vector<pipeline::SectionMatch> matches;
    std::vector<pipeline::SeriesSearch> searches;
    pipeline::SeriesFit fit;
    std::vector<double> prepareMs;
    std::vector<pipeline::SectionFeatures> sections;
};

core::Result<RunResult> runSeries(const std::vector<cv::Mat>& images,
                                  const std::vector<double>& umPerPx, const Stack& stack,
                                  const pipeline::SeriesMatchOptions& options, bool finish) {
    pipeline::SeriesMatcher matcher(stack.features, options);
    std::vector<pipeline::SectionFeatures> sections;
    RunResult out;
    for (size_t i = 0; i < images.size(); ++i) {
        const auto t = Clock::now();
        auto sec = pipeline::sectionFeatures(images[i], umPerPx[i], stack.workUm);
        if (!sec)
            return sec.error();
        out.prepareMs.push_back(msSince(t));
        auto m = matcher.add(*sec);
        if (!m)
            return m.error();
        sections.push_back(std::move(*sec));
        std::fprintf(stderr, "\r  section %zu/%zu", i + 1, images.size());
    }
    std::fprintf(stderr, "\n");
    if (finish)
        if (auto r = matcher.finish(sections); !r)
            return r.error();
    out.matches = matcher.matches();
    out.searches = matcher.searches();
    out.fit = matcher.fit();
    out.sections = std::move(sections);
    return out;
}

void printTable(const RunResult& r, const std::vector<double>& truthUm, bool candidates) {
    std::printf("%4s %9s %9s %9s %9s %7s %6s %6s %6s %6s %11s %7s %8s  %s\n", "sec", "truth_um",
                "match_um", "series_um", "line_um", "err_um", "slot", "score", "tiltC", "tiltR",
                "window", "prep", "ms", "anomaly");
    for (size_t i = 0; i < r.matches.size(); ++i) {
        const auto& m = r.matches[i];
        const auto& s = r.fit.sections[i];
        const auto& q = r.searches[i];
        const double t = i < truthUm.size() ? truthUm[i] : std::nan("");
        char window[32];
        if (q.windowed)
            std::snprintf(window, sizeof window, "%d-%d%s", q.first, q.last, q.fellBack ? "*" : "");
        else
            std::snprintf(window, sizeof window, "all");
        std::printf("%4zu %9.0f %9.0f %9.0f %9.0f %7.0f %6d %6.3f %6.1f %6.1f %11s %7.0f %8.0f  %s",
                    i + 1, t, m.positionUm, s.positionUm, s.predictedUm, s.positionUm - t, s.slot,
                    m.score, m.tiltColumnsDeg, m.tiltRowsDeg, window, r.prepareMs[i], q.ms,
                    std::string(pipeline::toString(s.anomaly)).c_str());
        if (s.missingBefore > 0)
            std::printf(" (%d)", s.missingBefore);
        std::printf("\n");
        if (candidates) {
            std::printf("      candidates:");
            for (size_t k = 0; k < m.candidates.size() && k < 8; ++k)
                std::printf(" %d:%.3f(o%.2f e%.2f r%.3f)", m.candidates[k].index,
                            m.candidates[k].score, m.candidates[k].overlap,
                            m.candidates[k].edgeAgreement, m.candidates[k].regionAgreement);
            std::printf("\n");
        }
    }
    std::printf("series fit: spacing %.1f um, origin %.0f um, inliers %d of %zu, sigma %.0f um, "
                "tilt columns(LR) %.2f rows(DV) %.2f deg from %d sections\n",
                r.fit.spacingUm, r.fit.originUm, r.fit.inliers, r.matches.size(), r.fit.sigmaUm,
                r.fit.tiltColumnsDeg, r.fit.tiltRowsDeg, r.fit.tiltSections);
}

void printTimes(const RunResult& r) {
    std::vector<double> total;
    for (size_t i = 0; i < r.matches.size(); ++i)
        total.push_back(r.prepareMs[i] + r.searches[i].ms);
    std::printf("time per section (prepare + live match) ms: median %.0f, max %.0f\n",
                percentile(total, 0.5), *std::max_element(total.begin(), total.end()));
}

} // namespace

int main(int argc, char** argv) {
    CLI::App app{"Series matching benchmark (issue 19)"};
    std::string shared = SLST_SHARED_DIR;
    std::string data = "all";
    double intervalUm = 100;
    bool finish = true, usePrior = true, tiltSearch = true;
    std::uint64_t seed = 5;
    double genTiltLr = 2.0, genTiltDv = -1.5;
    app.add_option("--shared", shared, "Shared data directory");
    app.add_option("--data", data, "generated|template|gerbi|mouse|all");
    app.add_option("--interval-um", intervalUm, "Stack interval");
    app.add_option("--seed", seed, "Generated series seed");
    app.add_option("--tilt-lr", genTiltLr, "Generated series: tilt toward the columns (deg)");
    app.add_option("--tilt-dv", genTiltDv, "Generated series: tilt toward the rows (deg)");
    double placeRatio = pipeline::SeriesModelOptions{}.placeScoreRatio;
    app.add_option("--place-ratio", placeRatio,
                   "Series model: place weak order-breaking matches on the line below this "
                   "fraction of the median score (0 = never)");
    app.add_flag("--finish,!--no-finish", finish, "Re-match off-line sections at the end");
    bool showCandidates = false;
    app.add_flag("--candidates", showCandidates,
                 "Print each section's eight best scored slices (index:score, agreements)");
    double orderWeight = pipeline::SeriesMatchOptions{}.orderWeight;
    app.add_option("--order-weight", orderWeight,
                   "finish(): weight of the spacing penalty in the series' Viterbi pass (0 = off)");
    app.add_flag("--prior,!--no-prior", usePrior,
                 "Give the model the series' spacing as the plan's interval");
    app.add_flag("--tilt-search,!--no-tilt-search", tiltSearch,
                 "Search the brain's tilt with tilted planes cut from the volume");
    std::string tiltMethod = "cross";
    app.add_option("--tilt-method", tiltMethod, "Tilt search: cross (parabolas) or grid")
        ->check(CLI::IsMember({"cross", "grid"}));
    pipeline::TiltSearchOptions tiltOptions;
    app.add_option("--tilt-fine-deg", tiltOptions.fineStepDeg, "Tilt search: last step (deg)");
    app.add_option("--tilt-sections", tiltOptions.sections,
                   "Tilt search: best-scoring on-line sections used");
    app.add_flag("--tilt-surface,!--no-tilt-surface", tiltOptions.surfaceFit,
                 "Tilt search (cross): finish with a quadratic surface over the scored tilts");
    CLI11_PARSE(app, argc, argv);
    tiltOptions.method =
        tiltMethod == "grid" ? pipeline::TiltSearchMethod::Grid : pipeline::TiltSearchMethod::Cross;
    const fs::path atlasDir = fs::path(shared) / "atlas" / "allen-ccf-2017";
    if (!fs::exists(atlasDir / "annotation_50.nrrd")) {
        std::printf("skipped: no Allen annotation under %s\n", shared.c_str());
        return 0;
    }
    auto volume = core::readNrrd(atlasDir / "annotation_50.nrrd");
    auto onto = core::readOntologyCsv(atlasDir / "structure_tree_safe_2017.csv");
    if (!volume || !onto) {
        std::fprintf(stderr, "cannot read the Allen files\n");
        return 1;
    }
    const double stackUmPerPx = 25;
    auto collapse = [&](const cv::Mat& l) {
        return pipeline::collapseLabels(l, *onto, pipeline::majorRegionIds(),
                                        pipeline::kOtherRegionId);
    };
    const auto t0 = Clock::now();
    auto cut = testing_atlas::majorRegionStack(*volume, *onto, intervalUm, stackUmPerPx);
    if (!cut) {
        std::fprintf(stderr, "%s\n", cut.error().message.c_str());
        return 1;
    }
    Stack stack;
    stack.workUm = cut->workUm;
    stack.features = std::move(cut->features);
    double planeMs = 0; // time spent cutting planes for the tilt search
    int planeCount = 0;
    const pipeline::PlaneFeatures planes = [&](double pos, double tc,
                                               double tr) -> core::Result<pipeline::SliceFeatures> {
        const auto tp = Clock::now();
        struct Add {
            double& ms;
            int& n;
            Clock::time_point t;
            ~Add() {
                ms += msSince(t);
                ++n;
            }
        } add{planeMs, planeCount, tp};
        auto g = pipeline::planeGeometry(
            *volume, pipeline::VolumeAxes::Allen,
            {pipeline::PlaneOrientation::Coronal, pos, tc, tr, stackUmPerPx});
        if (!g)
            return g.error();
        auto l = pipeline::sampleLabels(*volume, pipeline::VolumeAxes::Allen, *g);
        if (!l)
            return l.error();
        return pipeline::sliceFeatures(collapse(*l), stackUmPerPx, pos, stack.workUm);
    };
    auto searchTilt = [&](const RunResult& r) -> core::Result<pipeline::TiltEstimate> {
        const auto t = Clock::now();
        planeMs = 0;
        planeCount = 0;
        auto e = pipeline::searchSeriesTilt(r.sections, r.matches, r.fit, planes, tiltOptions);
        const double s = msSince(t) / 1000;
        if (e)
            std::printf(
                "tilt search with tilted planes (%s, %d sections, %d tilts, %.1f s = %.2f s "
                "per section of the series, of which %d planes cut in %.1f s): "
                "columns(LR) %.2f rows(DV) %.2f deg\n",
                tiltMethod.c_str(), e->sections, e->tiltsScored, s, s / double(r.matches.size()),
                planeCount, planeMs / 1000, e->tiltColumnsDeg, e->tiltRowsDeg);
        else
            std::printf("tilt search failed: %s\n", e.error().message.c_str());
        return e;
    };
    std::printf("stack: 50 um annotation (major regions), %zu coronal slices every %.0f um, "
                "%.0f ms\n",
                stack.features.size(), intervalUm, msSince(t0));
    int status = 0;

    if (data == "generated" || data == "all") {
        // 22 planned sections from 1800 um every 300 um, tilted (default 2.0 deg LR, -1.5 DV);
        // the section in slot 8 is lost (skip) and slots 14 and 15 are mounted swapped.
        const double spacing = 300, start = 1800, tiltC = genTiltLr, tiltR = genTiltDv;
        const std::vector<int> slots = skipAndSwapSlots();
        std::vector<cv::Mat> images;
        std::vector<double> umPerPx, truth;
        for (size_t i = 0; i < slots.size(); ++i) {
            const double pos = start + spacing * slots[i];
            auto g = pipeline::planeGeometry(
                *volume, pipeline::VolumeAxes::Allen,
                {pipeline::PlaneOrientation::Coronal, pos, tiltC, tiltR, 25});
            auto l = g ? pipeline::sampleLabels(*volume, pipeline::VolumeAxes::Allen, *g)
                       : core::Result<cv::Mat>(g.error());
            if (!l) {
                std::fprintf(stderr, "%s\n", l.error().message.c_str());
                return 1;
            }
            sim::GeneratorOptions go;
            go.seed = seed * 1000 + i;
            go.imageSize = {1000, 740};
            auto gen = sim::generateSection(collapse(*l), go);
            if (!gen) {
                std::fprintf(stderr, "generator: %s\n", gen.error().message.c_str());
                return 1;
            }
            const auto& a = gen->truth.affineAtlasFromImage;
            umPerPx.push_back(std::sqrt(std::abs(a(0, 0) * a(1, 1) - a(0, 1) * a(1, 0))) * 25);
            images.push_back(gen->image);
            truth.push_back(pos);
        }
        pipeline::SeriesMatchOptions o;
        o.model.placeScoreRatio = placeRatio;
        o.orderWeight = orderWeight;
        o.model.intervalUm = usePrior ? spacing : 0;
        std::printf("\n== generated series: %zu sections, spacing %.0f um, tilt LR %.1f DV %.1f "
                    "deg, slot 8 skipped, slots 14/15 swapped\n",
                    images.size(), spacing, tiltC, tiltR);
        auto r = runSeries(images, umPerPx, stack, o, finish);
        if (!r) {
            std::fprintf(stderr, "%s\n", r.error().message.c_str());
            return 1;
        }
        printTable(*r, truth, showCandidates);
        std::vector<double> err;
        for (size_t i = 0; i < truth.size(); ++i)
            err.push_back(std::abs(r->matches[i].positionUm - truth[i]));
        const auto& f = r->fit.sections;
        const auto [skip, swap] = plantedFound(f);
        int falseAlarms = 0, placed = 0;
        for (size_t i = 0; i < f.size(); ++i) {
            placed += f[i].anomaly == pipeline::SeriesAnomaly::Placed;
            falseAlarms += i != 8 && i != 13 && i != 14 &&
                           f[i].anomaly != pipeline::SeriesAnomaly::None &&
                           f[i].anomaly != pipeline::SeriesAnomaly::Placed;
        }
        std::vector<double> seriesErr;
        for (size_t i = 0; i < truth.size(); ++i)
            seriesErr.push_back(std::abs(f[i].positionUm - truth[i]));
        std::printf("generated, series answer (placed sections on the line): error median %.0f "
                    "um, 90th pct %.0f um; %d placed\n",
                    percentile(seriesErr, 0.5), percentile(seriesErr, 0.9), placed);
        std::printf("generated: position error median %.0f um, 90th pct %.0f um; skip detected %s, "
                    "swap detected %s, other sections flagged %d; spacing %.1f um (true %.0f); "
                    "tilt error LR %.2f DV %.2f deg\n",
                    percentile(err, 0.5), percentile(err, 0.9), skip ? "yes" : "NO",
                    swap ? "yes" : "NO", falseAlarms, r->fit.spacingUm, spacing,
                    r->fit.tiltColumnsDeg - tiltC, r->fit.tiltRowsDeg - tiltR);
        printTimes(*r);
        if (tiltSearch)
            if (auto e = searchTilt(*r))
                std::printf("generated: tilt error with tilted planes LR %.2f DV %.2f deg\n",
                            e->tiltColumnsDeg - tiltC, e->tiltRowsDeg - tiltR);
    }

    if (data == "template" || data == "all") {
        // Real contrast with known positions: planes of the Allen average template (two-photon
        // autofluorescence, 100 um voxels) at the generated series' slots, tilt and pixel size,
        // rotated and noised a little. Tells whether the matcher, given real tissue contrast
        // rather than the generator's painted regions, places sections with a bias.
        auto tmpl = core::readNrrd(atlasDir / "average_template_100.nrrd");
        if (!tmpl) {
            std::fprintf(stderr, "template: %s\n", tmpl.error().message.c_str());
            return 1;
        }
        const double spacing = 300, start = 1800;
        const std::vector<int> slots = skipAndSwapSlots();
        std::vector<cv::Mat> images;
        std::vector<double> umPerPx, truth;
        std::mt19937 rng(static_cast<unsigned>(seed));
        std::uniform_real_distribution<double> angle(-15, 15);
        for (size_t i = 0; i < slots.size(); ++i) {
            const double pos = start + spacing * slots[i];
            auto g = pipeline::planeGeometry(
                *tmpl, pipeline::VolumeAxes::Allen,
                {pipeline::PlaneOrientation::Coronal, pos, genTiltLr, genTiltDv, 50});
            auto v = g ? pipeline::sampleLabels(*tmpl, pipeline::VolumeAxes::Allen, *g)
                       : core::Result<cv::Mat>(g.error());
            if (!v) {
                std::fprintf(stderr, "%s\n", v.error().message.c_str());
                return 1;
            }
            cv::Mat f, big, rotated, img;
            v->convertTo(f, CV_32F);
            double lo = 0, hi = 0;
            cv::minMaxLoc(f, &lo, &hi);
            cv::resize(f, big, {}, 4, 4, cv::INTER_CUBIC); // 12.5 um per pixel
            const cv::Point2f c(float(big.cols) / 2, float(big.rows) / 2);
            const int side = int(std::max(big.cols, big.rows) * 1.2);
            cv::Mat rot = cv::getRotationMatrix2D(c, angle(rng), 1.0);
            rot.at<double>(0, 2) += (side - big.cols) / 2.0;
            rot.at<double>(1, 2) += (side - big.rows) / 2.0;
            cv::warpAffine(big, rotated, rot, {side, side}, cv::INTER_LINEAR, cv::BORDER_CONSTANT,
                           0);
            cv::Mat noise(rotated.size(), CV_32F);
            cv::randn(noise, 0, 0.03 * hi);
            rotated += noise;
            rotated.convertTo(img, CV_8U, 255.0 / std::max(hi, 1.0));
            images.push_back(img);
            umPerPx.push_back(12.5);
            truth.push_back(pos);
        }
        pipeline::SeriesMatchOptions o;
        o.model.placeScoreRatio = placeRatio;
        o.orderWeight = orderWeight;
        o.model.intervalUm = usePrior ? spacing : 0;
        std::printf("\n== template series: %zu sections of the average template, spacing %.0f "
                    "um, tilt LR %.1f DV %.1f deg, slot 8 skipped, slots 14/15 swapped\n",
                    images.size(), spacing, genTiltLr, genTiltDv);
        auto r = runSeries(images, umPerPx, stack, o, finish);
        if (!r) {
            std::fprintf(stderr, "%s\n", r.error().message.c_str());
            return 1;
        }
        printTable(*r, truth, showCandidates);
        std::vector<double> own, series, signedOwn;
        for (size_t i = 0; i < truth.size(); ++i) {
            own.push_back(std::abs(r->matches[i].positionUm - truth[i]));
            signedOwn.push_back(r->matches[i].positionUm - truth[i]);
            series.push_back(std::abs(r->fit.sections[i].positionUm - truth[i]));
        }
        const PlantedFound found = plantedFound(r->fit.sections);
        std::printf("template: own matches error median %.0f um, 90th pct %.0f, median signed "
                    "%+.0f um; series answer median %.0f, 90th pct %.0f; skip detected %s, swap "
                    "detected %s; spacing %.1f um\n",
                    percentile(own, 0.5), percentile(own, 0.9), percentile(signedOwn, 0.5),
                    percentile(series, 0.5), percentile(series, 0.9), found.skip ? "yes" : "NO",
                    found.swap ? "yes" : "NO", r->fit.spacingUm);
        printTimes(*r);
        std::printf("template: tilt error from the sections LR %.2f DV %.2f deg\n",
                    r->fit.tiltColumnsDeg - genTiltLr, r->fit.tiltRowsDeg - genTiltDv);
        if (tiltSearch)
            if (auto e = searchTilt(*r))
                std::printf("template: tilt error with tilted planes LR %.2f DV %.2f deg\n",
                            e->tiltColumnsDeg - genTiltLr, e->tiltRowsDeg - genTiltDv);
    }

    if (data == "gerbi" || data == "all") {
        const fs::path dir = fs::path(shared) / "sections" / "abba-gerbi-series";
        const auto rows = testing_abba::readGerbiRows(dir);
        if (!rows) {
            std::fprintf(stderr, "%s\n", rows.error().message.c_str());
            return 1;
        }
        std::vector<cv::Mat> images;
        std::vector<double> umPerPx, truth, abbaMm;
        for (const testing_abba::GerbiRow& row : *rows) {
            auto img = core::readImage(dir / row.file);
            if (!img) {
                std::fprintf(stderr, "%s: %s\n", row.file.c_str(), img.error().message.c_str());
                return 1;
            }
            images.push_back(*img);
            umPerPx.push_back(row.umPerPx);
            // ABBA's slicing-axis position, mm. ABBA (ReslicedAtlas.computeReslicedSources)
            // extends the atlas' extent along the slicing axis by 15% of its half-length on each
            // side and counts positions from the extended front: 0.15 x 13.2 mm / 2 = 0.99 mm
            // before the CCFv3 volume's front (docs/atlas.md). The stack counts from the first
            // voxel's centre (CCF coordinates: the NRRD's space origin is 0).
            abbaMm.push_back(row.abbaMm);
            truth.push_back(testing_abba::ccfUmFromAbbaMm(row.abbaMm));
        }
        const double abbaSpacing = 335.8;
        pipeline::SeriesMatchOptions o;
        o.model.placeScoreRatio = placeRatio;
        o.orderWeight = orderWeight;
        o.model.intervalUm = usePrior ? 300 : 0; // a nominal plan, not ABBA's spacing
        std::printf("\n== gerbi series: %zu sections (prior interval %.0f um)\n", images.size(),
                    o.model.intervalUm);
        auto r = runSeries(images, umPerPx, stack, o, finish);
        if (!r) {
            std::fprintf(stderr, "%s\n", r.error().message.c_str());
            return 1;
        }
        printTable(*r, truth, showCandidates);
        // ABBA: rotationX 0.042 rad about the left-right axis (the normal leans dorso-ventrally),
        // rotationY 0.0015 rad about the dorso-ventral axis (leans left-right). Signs of ABBA's
        // frame against ours are not established: compared by magnitude.
        const double abbaDv = 0.042 * 180 / kPi, abbaLr = 0.0015 * 180 / kPi;
        std::vector<double> own, series, signedOwn, readme, pos, ownPos;
        int placed = 0, flagged = 0;
        for (size_t i = 0; i < truth.size(); ++i) {
            const auto& s = r->fit.sections[i];
            own.push_back(std::abs(r->matches[i].positionUm - truth[i]));
            series.push_back(std::abs(s.positionUm - truth[i]));
            signedOwn.push_back(r->matches[i].positionUm - truth[i]);
            readme.push_back(std::abs(s.positionUm - abbaMm[i] * 1000));
            pos.push_back(s.positionUm);
            ownPos.push_back(r->matches[i].positionUm);
            placed += s.anomaly == pipeline::SeriesAnomaly::Placed;
            flagged += s.anomaly != pipeline::SeriesAnomaly::None &&
                       s.anomaly != pipeline::SeriesAnomaly::Placed;
        }
        std::printf("gerbi (ABBA frame: abba_position_mm - %.0f um): series answer error median "
                    "%.0f um, 90th pct %.0f um, max %.0f; own matches median %.0f, 90th pct %.0f, "
                    "median signed %+.0f um\n",
                    testing_abba::kSlicingMarginUm, percentile(series, 0.5),
                    percentile(series, 0.9), *std::max_element(series.begin(), series.end()),
                    percentile(own, 0.5), percentile(own, 0.9), percentile(signedOwn, 0.5));
        std::printf("gerbi (abba_position_mm read as CCF mm, as the README says): series answer "
                    "error median %.0f um, 90th pct %.0f um\n",
                    percentile(readme, 0.5), percentile(readme, 0.9));
        std::printf("gerbi: series answer inversions %d (Spearman %.4f), own matches %d (%.4f); "
                    "%d placed on the line, %d flagged; spacing %.1f um (ABBA %.1f, %+.1f%%); "
                    "|tilt| LR %.2f DV %.2f deg (ABBA %.2f / %.2f)\n",
                    inversions(pos), spearman(pos), inversions(ownPos), spearman(ownPos), placed,
                    flagged, r->fit.spacingUm, abbaSpacing,
                    100 * (r->fit.spacingUm / abbaSpacing - 1), std::abs(r->fit.tiltColumnsDeg),
                    std::abs(r->fit.tiltRowsDeg), abbaLr, abbaDv);
        printTimes(*r);
        if (tiltSearch)
            if (auto e = searchTilt(*r))
                std::printf("gerbi: |tilt| with tilted planes LR %.2f DV %.2f deg (ABBA %.2f / "
                            "%.2f)\n",
                            std::abs(e->tiltColumnsDeg), std::abs(e->tiltRowsDeg), abbaLr, abbaDv);
    }

    if (data == "mouse" || data == "all") {
        const fs::path dir = fs::path(shared) / "sections" / "abba-mouse-series";
        std::vector<cv::Mat> images;
        std::vector<double> umPerPx;
        for (int n = 1; n <= 20; ++n) {
            char name[32];
            std::snprintf(name, sizeof name, "Section-%02d.tif", n);
            auto img = core::readImage(dir / name);
            if (!img) {
                std::fprintf(stderr, "%s: %s\n", name, img.error().message.c_str());
                return 1;
            }
            images.push_back(*img);
            umPerPx.push_back(20);
        }
        pipeline::SeriesMatchOptions o;
        o.model.placeScoreRatio = placeRatio;
        o.orderWeight = orderWeight;
        o.model.intervalUm = 0; // no plan known for this series
        std::printf("\n== mouse series: 20 sections (no interval given)\n");
        auto r = runSeries(images, umPerPx, stack, o, finish);
        if (!r) {
            std::fprintf(stderr, "%s\n", r.error().message.c_str());
            return 1;
        }
        printTable(*r, {}, showCandidates);
        std::vector<double> pos, steps, ownPos;
        int placed = 0, flagged = 0;
        for (size_t i = 0; i < r->matches.size(); ++i) {
            const auto& s = r->fit.sections[i];
            pos.push_back(s.positionUm);
            ownPos.push_back(r->matches[i].positionUm);
            placed += s.anomaly == pipeline::SeriesAnomaly::Placed;
            flagged += s.anomaly != pipeline::SeriesAnomaly::None &&
                       s.anomaly != pipeline::SeriesAnomaly::Placed;
        }
        std::printf("mouse: own matches inversions %d (Spearman %.4f); series answer: %d placed "
                    "on the line, %d flagged\n",
                    inversions(ownPos), spearman(ownPos), placed, flagged);
        double worst = 0;
        for (size_t i = 1; i < pos.size(); ++i) {
            steps.push_back(pos[i] - pos[i - 1]);
            worst = std::max(worst, std::abs(steps.back() / r->fit.spacingUm - 1));
        }
        std::vector<double> absRes;
        for (const auto& s : r->fit.sections)
            absRes.push_back(std::abs(s.positionUm - s.predictedUm) / std::abs(r->fit.spacingUm));
        std::printf("mouse, series answer: inversions %d, Spearman %.4f; spacing %.1f um; "
                    "consecutive steps "
                    "median %.0f, min %.0f, max %.0f um (worst %.0f%% off the fit); residual / "
                    "spacing median %.0f%%, max %.0f%%\n",
                    inversions(pos), spearman(pos), r->fit.spacingUm, percentile(steps, 0.5),
                    *std::min_element(steps.begin(), steps.end()),
                    *std::max_element(steps.begin(), steps.end()), 100 * worst,
                    100 * percentile(absRes, 0.5),
                    100 * *std::max_element(absRes.begin(), absRes.end()));
        printTimes(*r);
    }
    return status;
}
