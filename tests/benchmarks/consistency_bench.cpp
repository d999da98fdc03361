// Real-tissue consistency (issue 17, item 3): each real section, warped by known random affine
// plus smooth deformations, must register to the same atlas mapping as the original. For every
// warp W (new image px q -> original px W(q)) and tissue point q, the difference
// |new(q) - original(W(q))| in atlas px; per (section, warp) its RMS over a dense grid of tissue
// points; per section the RMS over its warps; per series the median, mean and worst section.
//
// Atlas planes: abba-mouse-series by series matching without hints, as atlas_series.cpp does
// (100 um stack of the 50 um annotation, collapsed to the major regions, 25 um/px);
// abba-gerbi-series from its curated position and tilt (sections.csv, README), sliced from the
// 25 um annotation and collapsed the same way.
#include "../common/gerbi_series.hpp"
#include "../common/known_warp.hpp"
#include "../common/major_region_stack.hpp"
#include "slicestation/core/image_file.hpp"
#include "slicestation/core/nrrd.hpp"
#include "slicestation/core/ontology.hpp"
#include "slicestation/pipeline/affine.hpp"
#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/pipeline/atlas_matching.hpp"
#include "slicestation/pipeline/atlas_slicing.hpp"
#include "slicestation/pipeline/damage_series.hpp"
#include "slicestation/pipeline/overlay.hpp"
#include "slicestation/pipeline/registration.hpp"

#include <CLI/CLI.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <random>

using namespace slicestation;
namespace fs = std::filesystem;

using testing_warp::applyWarp;
using testing_warp::randomWarp;
using testing_warp::Warp;

namespace {

struct RealSection {
    std::string series, name;
    cv::Mat image;
    cv::Mat atlas; ///< collapsed labels, 25 um/px
    cv::Mat fine;  ///< every Allen id, same grid (the region warp's labels with --region-warp on)
    std::vector<std::int32_t> ventricles; ///< the Allen ids under 73 (ventricular systems)
    double umPerPx = 0;
};

std::vector<std::int32_t> ventricleIds(const core::Ontology& onto) {
    std::vector<std::int32_t> ids;
    for (const auto& st : onto.structures())
        if (onto.isDescendantOf(st.id, 73))
            ids.push_back(static_cast<std::int32_t>(st.id));
    return ids;
}

double median(std::vector<double> v) {
    if (v.empty())
        return 0;
    std::sort(v.begin(), v.end());
    return v.size() % 2 ? v[v.size() / 2] : 0.5 * (v[v.size() / 2 - 1] + v[v.size() / 2]);
}

core::Result<std::vector<RealSection>> mouseSeries(const fs::path& shared) {
    const fs::path atlasDir = shared / "atlas" / "allen-ccf-2017";
    const fs::path dir = shared / "sections" / "abba-mouse-series";
    auto volume = core::readNrrd(atlasDir / "annotation_50.nrrd");
    if (!volume)
        return volume.error();
    auto onto = core::readOntologyCsv(atlasDir / "structure_tree_safe_2017.csv");
    if (!onto)
        return onto.error();
    const double stackUm = 25, sectionUm = 20;
    auto stack = testing_atlas::majorRegionStack(*volume, *onto, 100, stackUm);
    if (!stack)
        return stack.error();
    const std::vector<cv::Mat>& labels = stack->labels;
    const double workUm = stack->workUm;
    std::vector<RealSection> out;
    std::vector<pipeline::SectionFeatures> sections;
    for (int n = 1; n <= 20; ++n) {
        char name[32];
        std::snprintf(name, sizeof name, "Section-%02d.tif", n);
        auto image = core::readImage(dir / name);
        if (!image)
            return image.error();
        auto f = pipeline::sectionFeatures(*image, sectionUm, workUm);
        if (!f)
            return f.error();
        sections.push_back(std::move(*f));
        out.push_back({"mouse", name, *image, {}, {}, ventricleIds(*onto), sectionUm});
    }
    auto match = pipeline::matchSeries(sections, stack->features);
    if (!match)
        return match.error();
    for (size_t i = 0; i < out.size(); ++i) {
        out[i].atlas = labels[size_t((*match)[i].index)];
        out[i].fine = stack->slices[size_t((*match)[i].index)].labels;
    }
    return out;
}

core::Result<std::vector<RealSection>> gerbiSeries(const fs::path& shared) {
    const fs::path atlasDir = shared / "atlas" / "allen-ccf-2017";
    const fs::path dir = shared / "sections" / "abba-gerbi-series";
    auto volume = core::readNrrd(atlasDir / "annotation_25_quicknii.nrrd");
    if (!volume)
        return volume.error();
    auto onto = core::readOntologyCsv(atlasDir / "structure_tree_safe_2017.csv");
    if (!onto)
        return onto.error();
    auto rows = testing_abba::readGerbiRows(dir);
    if (!rows)
        return rows.error();
    std::vector<RealSection> out;
    for (const testing_abba::GerbiRow& row : *rows) {
        auto image = core::readImage(dir / row.file);
        if (!image)
            return image.error();
        auto labels = testing_abba::gerbiPlaneLabels(*volume, row.abbaMm);
        if (!labels)
            return labels.error();
        out.push_back({"gerbi", row.file, *image,
                       pipeline::collapseLabels(*labels, *onto, pipeline::majorRegionIds(),
                                                pipeline::kOtherRegionId),
                       *labels, ventricleIds(*onto), row.umPerPx});
    }
    return out;
}

} // namespace

static const char* verdictText(pipeline::DamageVerdict v) {
    return v == pipeline::DamageVerdict::Damaged             ? "DAMAGED"
           : v == pipeline::DamageVerdict::CheckRegistration ? "CHECK_REG"
                                                             : "clean";
}

/// The sections' damage judged by eye (the series' README files): torn, unclear, else clean.
static char truthOf(const std::string& series, int number) {
    const std::vector<int> torn =
        series == "mouse" ? std::vector<int>{9, 11, 14, 15} : std::vector<int>{2, 14};
    const std::vector<int> unclear =
        series == "mouse" ? std::vector<int>{10, 13} : std::vector<int>{1, 3, 11, 12, 13, 17, 18};
    if (std::find(torn.begin(), torn.end(), number) != torn.end())
        return 'T';
    if (std::find(unclear.begin(), unclear.end(), number) != unclear.end())
        return '?';
    return 'c';
}

/// Series context (issue 18, item 5): each section judged again with what the sections
/// registered before it in this run show (their gaps, and their glass where their atlas expects
/// tissue, atlas px: pipeline::shownInSeries), as the station does live (the
/// `window` nearest earlier ones), and, for comparison only, with one section on either side
/// (what waiting for the next section would give). The slices of one series share the atlas
/// pixel grid (checked: every section's atlas has the same size), so atlas px compare places.
struct JudgedSection {
    std::string name;
    int number = 0;
    pipeline::Registration reg;
    cv::Size atlasSize;
};

static void printSeriesContext(const std::string& series, const std::vector<JudgedSection>& run,
                               const pipeline::SeriesContextParams& params) {
    std::vector<pipeline::SectionShown> outlines;
    for (const JudgedSection& s : run) {
        outlines.push_back(pipeline::shownInSeries(s.reg));
        if (s.atlasSize != run.front().atlasSize)
            std::printf("series %s: %s's atlas is %dx%d, not %dx%d: atlas px do not compare\n",
                        series.c_str(), s.name.c_str(), s.atlasSize.width, s.atlasSize.height,
                        run.front().atlasSize.width, run.front().atlasSize.height);
    }
    const pipeline::DamageParams dp;
    int counts[3][3] = {}; // [alone, live, both sides][torn caught, clean flagged, unclear flagged]
    int torn = 0, clean = 0, unclear = 0;
    std::printf("series context %s (window %d earlier, slack %.1f atlas px, same place %.2f):\n",
                series.c_str(), params.window, params.slackAtlasPx, params.samePlaceShare);
    for (std::size_t i = 0; i < run.size(); ++i) {
        std::vector<pipeline::SectionShown> earlier, around;
        for (std::size_t k = 1; k <= std::size_t(params.window) && k <= i; ++k)
            earlier.push_back(outlines[i - k]);
        if (i > 0)
            around.push_back(outlines[i - 1]);
        if (i + 1 < run.size())
            around.push_back(outlines[i + 1]);
        pipeline::Registration live = run[i].reg, both = run[i].reg;
        pipeline::judgeInSeries(live, earlier, dp, params);
        pipeline::SeriesContextParams bothParams = params;
        bothParams.contiguous = false; // each side's neighbour is the nearest of its side
        pipeline::judgeInSeries(both, around, dp, bothParams);
        const char truth = truthOf(series, run[i].number);
        torn += truth == 'T';
        clean += truth == 'c';
        unclear += truth == '?';
        const pipeline::Registration* judged[3] = {&run[i].reg, &live, &both};
        for (int j = 0; j < 3; ++j)
            if (judged[j]->damageVerdict == pipeline::DamageVerdict::Damaged)
                ++counts[j][truth == 'T' ? 0 : truth == 'c' ? 1 : 2];
        std::printf("context %-6s %-16s %s alone %-9s %.3f | live %-9s %.3f | both sides %-9s "
                    "%.3f |",
                    series.c_str(), run[i].name.c_str(),
                    truth == 'T'   ? "torn   "
                    : truth == '?' ? "unclear"
                                   : "clean  ",
                    verdictText(run[i].reg.damageVerdict), run[i].reg.damageScore,
                    verdictText(live.damageVerdict), live.damageScore,
                    verdictText(both.damageVerdict), both.damageScore);
        for (std::size_t r = 0; r < live.damage.size(); ++r)
            std::printf(" %s %.2f%% p%.1f/%.1f", std::string(toString(live.damage[r].kind)).c_str(),
                        100 * live.damage[r].share, live.damage[r].persistence,
                        both.damage[r].persistence);
        std::printf("\n");
    }
    const char* names[3] = {"alone", "live (earlier)", "both sides"};
    for (int j = 0; j < 3; ++j)
        std::printf("context %-6s %-15s torn caught %d of %d, clean flagged %d of %d, unclear "
                    "flagged %d of %d\n",
                    series.c_str(), names[j], counts[j][0], torn, counts[j][1], clean, counts[j][2],
                    unclear);
    std::fflush(stdout);
}

/// One line per section: verdict, score and every region (kind, share, length and thickness as
/// shares of the brain width, score).
static void printDamage(const std::string& series, const std::string& name,
                        const pipeline::Registration& reg) {
    const char* verdict = reg.damageVerdict == pipeline::DamageVerdict::Damaged ? "DAMAGED"
                          : reg.damageVerdict == pipeline::DamageVerdict::CheckRegistration
                              ? "CHECK_REG"
                              : "clean";
    std::printf("damage %-6s %-16s %-9s score %.3f", series.c_str(), name.c_str(), verdict,
                reg.damageScore);
    if (reg.quality.regionWarpExplainedBefore > 0) // the region warp ran (--region-warp on)
        std::printf(" rwarp %.3f -> %.3f%s", reg.quality.regionWarpExplainedBefore,
                    reg.quality.regionWarpExplainedAfter,
                    reg.quality.regionWarpKept ? " kept" : "");
    const double bw = std::max(1.0, reg.brainWidthPx);
    for (const pipeline::DamageRegion& d : reg.damage) {
        // Where it lies: its box in working px (as the overlay shows it).
        cv::Rect2f box;
        if (!d.polygon.empty()) {
            std::vector<cv::Point2f> w;
            for (const cv::Point2f& p : d.polygon)
                w.emplace_back(reg.workingFromImage(p));
            box = cv::boundingRect(w);
        }
        std::printf(" [%s %.2f%% len %.3f thick %.3f score %.2f excess %.2f (vent %.2f)%s at "
                    "%.0f,%.0f %.0fx%.0f mirror %.2f]",
                    std::string(pipeline::toString(d.kind)).c_str(), 100 * d.share, d.lengthPx / bw,
                    d.thicknessPx / bw, d.score, d.excessShare, d.excessVentricleShare,
                    d.misfit ? " MISFIT" : "", box.x, box.y, box.width, box.height, d.mirrorShare);
    }
    std::printf("\n");
}

int main(int argc, char** argv) {
    CLI::App app{"Real-tissue consistency of the registration under known warps"};
    std::string shared = SLST_SHARED_DIR, seriesText = "all", csvPath, overlayDir;
    int warps = 10, sectionsPerSeries = 1000;
    std::uint64_t seed = 17;
    std::vector<int> only;
    bool shiftOnly = false;
    double fieldScale = 1.0, maxTurnDeg = 180;
    std::string smoothMode = "on";
    app.add_flag("--shift-only", shiftOnly,
                 "Warps are whole-pixel shifts only (checks the benchmark: RMS near 0 expected)");
    bool sameFrame = false;
    app.add_flag("--same-frame", sameFrame,
                 "With --shift-only: shifts of up to 4% each way inside the image's own frame "
                 "instead of into a 15% larger one");
    bool stages = false;
    app.add_flag("--stages", stages,
                 "Also the difference of each affine stage's map (obb, outline, icp, intensity) "
                 "per series: median over the (section, warp) pairs that are not gross");
    app.add_option("--field-scale", fieldScale,
                   "Scale of the warps' smooth field (1 = 1% of the longer side, s.d.; 0 = none)")
        ->check(CLI::Range(0.0, 10.0));
    app.add_option("--max-turn", maxTurnDeg,
                   "The registration's mounting rule: sections turned at most this far (degrees; "
                   "180 = any way, the default)")
        ->check(CLI::Range(0.0, 180.0));
    app.add_option("--smooth", smoothMode,
                   "The registration's smooth (B-spline) warp: on (the default) | off")
        ->check(CLI::IsMember({"on", "off"}));
    std::string regionWarpMode = "off";
    app.add_option("--region-warp", regionWarpMode,
                   "The region warp, painting every Allen id of the section's plane: on | off")
        ->check(CLI::IsMember({"on", "off"}));
    double rwarpMaxSpread = pipeline::RegionWarpOptions{}.maxInnerSpread;
    app.add_option(
           "--rwarp-max-spread", rwarpMaxSpread,
           "RegionWarpOptions::maxInnerSpread: regions spread inside beyond this many times "
           "the typical region are left out of the region warp's fit (0: none)")
        ->check(CLI::Range(0.0, 100.0));
    std::string refineMode = "on";
    app.add_option("--refine", refineMode,
                   "The registration's dense refinement: on (the default) | off")
        ->check(CLI::IsMember({"on", "off"}));
    std::string edgeWithRegions =
        pipeline::RegistrationOptions{}.edgeWarpWithRegions ? "on" : "off";
    app.add_option("--edge-warp-with-regions", edgeWithRegions,
                   "RegistrationOptions::edgeWarpWithRegions: the edge warps before the region "
                   "warp when it runs: on | off (default: the product's)")
        ->check(CLI::IsMember({"on", "off"}));
    double pullBelow = pipeline::RegistrationOptions{}.outlinePullBelowOverlap;
    app.add_option("--pull-below", pullBelow,
                   "RegistrationOptions::outlinePullBelowOverlap: the outline pull's gate on the "
                   "affine's tissue overlap")
        ->check(CLI::Range(0.0, 2.0));
    double crackDarkness = pipeline::DamageParams{}.crackDarkness;
    app.add_option("--crack-darkness", crackDarkness,
                   "DamageParams::crackDarkness (0: cracks must show glass, as before 2026-12-02)")
        ->check(CLI::Range(0.0, 1.0));
    std::string mirroredGaps = "on";
    std::string foldCrease = "on";
    app.add_option("--fold-crease", foldCrease,
                   "DamageParams::foldFromCrease: a fold's band from the crease as deep as the gap "
                   "(off: a band as deep as the gap all round it)")
        ->check(CLI::IsMember({"on", "off"}));
    app.add_option("--mirrored-gaps", mirroredGaps,
                   "DamageParams::leaveOutMirroredGaps: gaps with a mirrored twin left out")
        ->check(CLI::IsMember({"on", "off"}));
    std::string crackPieces = "on";
    app.add_option("--crack-pieces", crackPieces,
                   "DamageParams::crackPieceFrac: a tear followed across a break to the pieces of "
                   "crack beyond it (off: crackPieceFrac 0)")
        ->check(CLI::IsMember({"on", "off"}));
    int foldRepairs = pipeline::RegistrationOptions{}.foldRepairs;
    app.add_option("--fold-repairs", foldRepairs,
                   "RegistrationOptions::foldRepairs: rounds of relaxing the final warp where "
                   "its map folds (0: keep the folds)")
        ->check(CLI::Range(0, 10));
    bool damageOnly = false;
    pipeline::SeriesContextParams contextParams;
    app.add_option("--context-window", contextParams.window,
                   "Series context: earlier sections looked at (SeriesContextParams::window)")
        ->check(CLI::Range(1, 10));
    app.add_option("--context-slack", contextParams.slackAtlasPx,
                   "Series context: the registration slack in atlas px")
        ->check(CLI::Range(0.0, 50.0));
    app.add_option("--context-share", contextParams.samePlaceShare,
                   "Series context: share of a gap a neighbour must cover to be the same place")
        ->check(CLI::Range(0.0, 1.0));
    app.add_flag("--damage", damageOnly,
                 "Register each original only and print its damage verdict, score and regions "
                 "(no warps)");
    app.add_option("--shared", shared, "Path of ../shared");
    app.add_option("--series", seriesText, "mouse | gerbi | all")
        ->check(CLI::IsMember({"mouse", "gerbi", "all"}));
    app.add_option("--warps", warps, "Known warps per section")->check(CLI::Range(1, 100));
    app.add_option("--sections", sectionsPerSeries, "First N sections of each series")
        ->check(CLI::Range(1, 1000));
    app.add_option("--only", only, "Only these section numbers (1-based) of each series");
    app.add_option("--seed", seed, "Seed of the warps");
    app.add_option("--csv", csvPath, "Per (section, warp) rows here");
    app.add_option("--overlays", overlayDir,
                   "Write the overlay of each original and warped registration here (PNG)");
    CLI11_PARSE(app, argc, argv);
    const fs::path sh(shared);
    if (!fs::exists(sh / "sections" / "abba-mouse-series") ||
        !fs::exists(sh / "atlas" / "allen-ccf-2017" / "annotation_25_quicknii.nrrd")) {
        std::fprintf(stderr, "the real series or the Allen atlas are missing under %s\n",
                     shared.c_str());
        return 1;
    }
    std::ofstream csv;
    if (!csvPath.empty()) {
        csv.open(csvPath);
        csv << "series,section,warp,rms,max,points,seconds_original,seconds_warped,"
               "overlap_original,overlap_warped,verdict_original,verdict_warped,"
               "score_original,score_warped\n";
    }
    std::printf("%-6s %-16s %5s %8s %8s %8s %8s  %s\n", "series", "section", "warps", "RMS",
                "worst", "max", "overlap",
                "damage: eye, original's verdict, warped copies flagged");
    struct SeriesResult {
        std::string name;
        std::vector<double> sectionRms;
        std::vector<std::string> sectionNames;
        double allSq = 0;
        long allN = 0;
        int failed = 0;
        int warpsDone = 0, grossWarps = 0; ///< gross: a warp's RMS over 25 px (a flip or jump)
        std::vector<double> warpRms;       ///< every (section, warp) RMS that is not gross
        /// --stages: stage name -> the RMS of that affine stage's map for every pair not gross
        std::vector<std::pair<std::string, std::vector<double>>> stageRms;
        /// Damage verdicts by the series' eye judgement (0 torn, 1 clean, 2 unclear): originals
        /// [0] and warped copies [1] judged, flagged DAMAGED, CHECK_REG; warped copies whose
        /// verdict is the original's.
        int judged[3][2] = {}, flagged[3][2] = {}, checkReg[3][2] = {}, same[3] = {};
    };
    std::vector<SeriesResult> results;
    for (const std::string series : {"mouse", "gerbi"}) {
        if (seriesText != "all" && seriesText != series)
            continue;
        auto secs = series == "mouse" ? mouseSeries(sh) : gerbiSeries(sh);
        if (!secs) {
            std::fprintf(stderr, "%s series: %s\n", series.c_str(), secs.error().message.c_str());
            return 1;
        }
        SeriesResult res;
        res.name = series;
        std::vector<JudgedSection> judged; // --damage: the sections registered, in series order
        std::mt19937_64 rng(seed);
        for (size_t si = 0; si < secs->size() && int(si) < sectionsPerSeries; ++si) {
            if (!only.empty() && std::find(only.begin(), only.end(), int(si) + 1) == only.end())
                continue;
            const RealSection& s = (*secs)[si];
            pipeline::RegistrationOptions ro;
            ro.imageUmPerPx = s.umPerPx;
            ro.atlasUmPerPx = 25;
            ro.maxTurnDeg = maxTurnDeg;
            ro.smoothWarp = smoothMode == "on";
            ro.foldRepairs = foldRepairs;
            ro.edgeWarpWithRegions = edgeWithRegions == "on";
            ro.denseRefine = refineMode == "on";
            if (regionWarpMode == "on" && s.fine.type() == CV_32S &&
                s.fine.size() == s.atlas.size()) {
                ro.regionLabels = s.fine;
                ro.regionWarpOptions.glassIds = s.ventricles;
            }
            ro.regionWarpOptions.maxInnerSpread = rwarpMaxSpread;
            ro.damage.crackDarkness = crackDarkness;
            ro.outlinePullBelowOverlap = pullBelow;
            ro.damage.leaveOutMirroredGaps = mirroredGaps == "on";
            ro.damage.foldFromCrease = foldCrease == "on";
            if (crackPieces == "off")
                ro.damage.crackPieceFrac = 0;
            const auto t0 = std::chrono::steady_clock::now();
            auto reg0 = pipeline::registerSection(s.image, s.atlas, ro);
            const double sec0 =
                std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
            if (!reg0) {
                std::fprintf(stderr, "%s %s: original failed: %s\n", series.c_str(), s.name.c_str(),
                             reg0.error().message.c_str());
                ++res.failed;
                continue;
            }
            auto writeOverlay = [&](const pipeline::Registration& r, const std::string& tag) {
                if (overlayDir.empty())
                    return;
                fs::create_directories(overlayDir);
                const fs::path path =
                    fs::path(overlayDir) /
                    (series + "-" + fs::path(s.name).stem().string() + "-" + tag + ".png");
                cv::imwrite(path.string(), pipeline::renderOverlay(r, s.atlas));
            };
            writeOverlay(*reg0, "original");
            if (damageOnly) {
                printDamage(series, s.name, *reg0);
                judged.push_back({s.name, int(si) + 1, *reg0, s.atlas.size()});
                continue;
            }
            if (!overlayDir.empty()) {
                cv::Mat grey;
                cv::Mat(s.atlas != 0).convertTo(grey, CV_32F, 0.5 / 255);
                cv::imwrite((fs::path(overlayDir) /
                             (series + "-" + fs::path(s.name).stem().string() + "-atlas.png"))
                                .string(),
                            pipeline::renderOverlay(grey, s.atlas));
            }
            // The original's tissue at full resolution.
            cv::Mat tissue;
            cv::resize(reg0->workingTissueMask, tissue, s.image.size(), 0, 0, cv::INTER_NEAREST);
            double sq = 0, worstWarp = 0, worstPoint = 0;
            long n = 0;
            int copiesFlagged = 0;
            const char eye = truthOf(series, int(si) + 1);
            const int cls = eye == 'T' ? 0 : eye == 'c' ? 1 : 2;
            const auto tally = [&](const pipeline::Registration& r, int which) {
                ++res.judged[cls][which];
                res.flagged[cls][which] += r.damageVerdict == pipeline::DamageVerdict::Damaged;
                res.checkReg[cls][which] +=
                    r.damageVerdict == pipeline::DamageVerdict::CheckRegistration;
            };
            tally(*reg0, 0);
            for (int k = 0; k < warps; ++k) {
                const Warp w = randomWarp(rng, s.image.size(), shiftOnly, fieldScale, sameFrame);
                const cv::Mat warped = applyWarp(s.image, w);
                const auto t1 = std::chrono::steady_clock::now();
                auto reg1 = pipeline::registerSection(warped, s.atlas, ro);
                const double sec1 =
                    std::chrono::duration<double>(std::chrono::steady_clock::now() - t1).count();
                if (!reg1) {
                    std::fprintf(stderr, "%s %s warp %d: failed: %s\n", series.c_str(),
                                 s.name.c_str(), k, reg1.error().message.c_str());
                    ++res.failed;
                    continue;
                }
                writeOverlay(*reg1, "warp" + std::to_string(k));
                tally(*reg1, 1);
                copiesFlagged += reg1->damageVerdict == pipeline::DamageVerdict::Damaged;
                res.same[cls] += reg1->damageVerdict == reg0->damageVerdict;
                // A dense grid of tissue points of the warped image (about 150 per side).
                const testing_warp::WarpDifference diff = testing_warp::differenceOverTissue(
                    w, tissue, [&](cv::Point2d q) { return reg1->atlasFromImage(q); },
                    [&](cv::Point2d p) { return reg0->atlasFromImage(p); });
                const double wsq = diff.sumSq, wmax = diff.max;
                const long wn = diff.points;
                if (wn == 0)
                    continue;
                const double rms = std::sqrt(wsq / double(wn));
                ++res.warpsDone;
                const bool gross = rms > 25;
                if (gross)
                    ++res.grossWarps;
                else
                    res.warpRms.push_back(rms);
                // Each affine stage's map on its own (the stages both registrations went through).
                for (size_t st = 0; stages && !gross && st < reg1->stageAffines.size(); ++st) {
                    const std::string& name = reg1->stageAffines[st].first;
                    const cv::Matx23d a1 = reg1->stageAffines[st].second;
                    const auto a0 =
                        std::find_if(reg0->stageAffines.begin(), reg0->stageAffines.end(),
                                     [&](const auto& e) { return e.first == name; });
                    if (a0 == reg0->stageAffines.end())
                        continue;
                    const double stageRms =
                        testing_warp::differenceOverTissue(
                            w, tissue,
                            [&](cv::Point2d q) {
                                return pipeline::apply(a1, reg1->workingFromImage(q));
                            },
                            [&](cv::Point2d q) {
                                return pipeline::apply(a0->second, reg0->workingFromImage(q));
                            })
                            .rms();
                    auto slot = std::find_if(res.stageRms.begin(), res.stageRms.end(),
                                             [&](const auto& e) { return e.first == name; });
                    if (slot == res.stageRms.end())
                        slot = res.stageRms.insert(res.stageRms.end(), {name, {}});
                    slot->second.push_back(stageRms);
                }
                sq += wsq;
                n += wn;
                worstWarp = std::max(worstWarp, rms);
                worstPoint = std::max(worstPoint, wmax);
                if (csv)
                    csv << series << ',' << s.name << ',' << k << ',' << rms << ',' << wmax << ','
                        << wn << ',' << sec0 << ',' << sec1 << ',' << reg0->quality.tissueOverlap
                        << ',' << reg1->quality.tissueOverlap << ','
                        << verdictText(reg0->damageVerdict) << ','
                        << verdictText(reg1->damageVerdict) << ',' << reg0->damageScore << ','
                        << reg1->damageScore << '\n';
            }
            if (n == 0)
                continue;
            const double rms = std::sqrt(sq / double(n));
            res.sectionRms.push_back(rms);
            res.sectionNames.push_back(s.name);
            res.allSq += sq;
            res.allN += n;
            std::printf("%-6s %-16s %5d %8.2f %8.2f %8.2f %8.2f  %c %-9s %d\n", series.c_str(),
                        s.name.c_str(), warps, rms, worstWarp, worstPoint,
                        reg0->quality.tissueOverlap, eye, verdictText(reg0->damageVerdict),
                        copiesFlagged);
            std::fflush(stdout);
        }
        if (damageOnly && !judged.empty())
            printSeriesContext(series, judged, contextParams);
        results.push_back(res);
    }
    std::printf("\n%-6s %8s %8s %8s %8s %-22s %7s %12s %14s\n", "series", "sections", "median",
                "mean", "pooled", "worst section", "failed", "gross warps", "median w/o gross");
    for (const auto& r : results) {
        if (r.sectionRms.empty()) {
            std::printf("%-6s no section registered\n", r.name.c_str());
            continue;
        }
        const auto worst = std::max_element(r.sectionRms.begin(), r.sectionRms.end());
        double mean = 0;
        for (double v : r.sectionRms)
            mean += v;
        mean /= double(r.sectionRms.size());
        char w[64];
        std::snprintf(w, sizeof w, "%.2f (%s)", *worst,
                      r.sectionNames[size_t(worst - r.sectionRms.begin())].c_str());
        char g[32];
        std::snprintf(g, sizeof g, "%d of %d", r.grossWarps, r.warpsDone);
        std::printf("%-6s %8zu %8.2f %8.2f %8.2f %-22s %7d %12s %14.2f\n", r.name.c_str(),
                    r.sectionRms.size(), median(r.sectionRms), mean,
                    std::sqrt(r.allSq / double(std::max(1L, r.allN))), w, r.failed, g,
                    median(r.warpRms));
    }
    // The damage check on the same tissue under known warps: a verdict a technician can trust
    // does not change when the section is mounted a little differently.
    std::printf("\ndamage verdicts, originals and their warped copies (the same tissue under a "
                "known warp; flagged = DAMAGED, check = CHECK_REG):\n");
    for (const auto& r : results) {
        static const char* kClass[3] = {"torn", "clean", "unclear"};
        for (int c = 0; c < 3; ++c) {
            if (r.judged[c][0] == 0)
                continue;
            std::printf("%-6s %-8s originals flagged %2d / check %2d of %2d | warped copies "
                        "flagged %3d / check %3d of %3d (%.1f%% flagged) | same verdict as the "
                        "original %3d of %3d\n",
                        r.name.c_str(), kClass[c], r.flagged[c][0], r.checkReg[c][0],
                        r.judged[c][0], r.flagged[c][1], r.checkReg[c][1], r.judged[c][1],
                        100.0 * r.flagged[c][1] / std::max(1, r.judged[c][1]), r.same[c],
                        r.judged[c][1]);
        }
    }
    for (const auto& r : results) {
        if (r.stageRms.empty())
            continue;
        std::printf("%-6s stages, median RMS of the pairs not gross:", r.name.c_str());
        for (const auto& [name, v] : r.stageRms)
            std::printf(" %s %.2f (%zu)", name.c_str(), median(v), v.size());
        std::printf(" | final %.2f (%zu)\n", median(r.warpRms), r.warpRms.size());
    }
    std::printf("(RMS difference in atlas px of 25 um between the warped section's registration "
                "and the original's composed with the known warp, over a grid of the original's "
                "tissue; per section over its warps; pooled = over all points of the series; gross "
                "warps = (section, warp) pairs whose RMS exceeds 25 px, a flipped or jumped "
                "placement; the last column is the median (section, warp) RMS of the others)\n");
    return 0;
}
