// Matching sections generated from known planes against a stack (built-in atlas: no data
// needed, fast and deterministic).
#include "slicestation/core/image_file.hpp"
#include "slicestation/core/nrrd.hpp"
#include "slicestation/core/ontology.hpp"
#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/pipeline/atlas_matching.hpp"
#include "slicestation/pipeline/atlas_slicing.hpp"
#include "slicestation/pipeline/series_matching.hpp"
#include "slicestation/sim/builtin_atlas.hpp"
#include "slicestation/sim/section_generator.hpp"

#include <gtest/gtest.h>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

using namespace slicestation;
using namespace slicestation::pipeline;

namespace {

constexpr double kLengthUm = 8000, kIntervalUm = 200, kUmPerPx = 25;

std::vector<SliceFeatures> builtinStack(double& workUm) {
    std::vector<cv::Mat> labels;
    for (double p = 0; p <= kLengthUm; p += kIntervalUm)
        labels.push_back(sim::builtinAtlasPlane(p / kLengthUm));
    workUm = matchWorkUmPerPx(labels, kUmPerPx);
    std::vector<SliceFeatures> f;
    for (size_t i = 0; i < labels.size(); ++i)
        f.push_back(sliceFeatures(labels[i], kUmPerPx, double(i) * kIntervalUm, workUm));
    return f;
}

/// The stack the real gerbi tests match against: the 50 um Allen annotation cut coronally every
/// 100 um, collapsed to the major regions; `workUm` gets its working pixel size. Empty, with the
/// reason in `error`, when the atlas cannot be read or sliced.
std::vector<SliceFeatures> allenStack100um(const std::filesystem::path& atlas, double& workUm,
                                           std::string& error) {
    auto volume = core::readNrrd(atlas / "annotation_50.nrrd");
    auto onto = core::readOntologyCsv(atlas / "structure_tree_safe_2017.csv");
    if (!volume || !onto) {
        error = !volume ? volume.error().message : onto.error().message;
        return {};
    }
    auto slices =
        sliceVolume(*volume, VolumeAxes::Allen, {PlaneOrientation::Coronal, 0, 100, 0, 0, 25});
    if (!slices) {
        error = slices.error().message;
        return {};
    }
    std::vector<cv::Mat> labels;
    for (auto& sl : *slices)
        labels.push_back(collapseLabels(sl.labels, *onto, majorRegionIds(), 8));
    workUm = matchWorkUmPerPx(labels, 25);
    std::vector<SliceFeatures> stack;
    for (size_t i = 0; i < labels.size(); ++i)
        stack.push_back(sliceFeatures(labels[i], 25, (*slices)[i].geometry.positionUm, workUm));
    return stack;
}

} // namespace

TEST(AtlasMatching, FindsThePlaneOfGeneratedSections) {
    double workUm = 0;
    const auto stack = builtinStack(workUm);
    ASSERT_EQ(stack.size(), 41u);
    int seed = 3;
    for (double pos : {1500.0, 3300.0, 5000.0, 6900.0}) {
        sim::GeneratorOptions go;
        go.seed = std::uint64_t(seed++);
        go.imageSize = {900, 660};
        auto gen = sim::generateSection(sim::builtinAtlasPlane(pos / kLengthUm), go);
        ASSERT_TRUE(gen.ok()) << gen.error().message;
        const auto& a = gen->truth.affineAtlasFromImage;
        const double imageUm =
            std::sqrt(std::abs(a(0, 0) * a(1, 1) - a(0, 1) * a(1, 0))) * kUmPerPx;
        auto sec = sectionFeatures(gen->image, imageUm, workUm);
        ASSERT_TRUE(sec.ok()) << sec.error().message;
        auto m = matchSection(*sec, stack);
        ASSERT_TRUE(m.ok()) << m.error().message;
        // Three slices (600 um of 8000): the built-in brain changes slowly at mid levels, so
        // neighbouring slices are nearly alike; the accuracy on the real atlas is measured by
        // slst_bench_atlas_match.
        EXPECT_LE(std::abs(m->positionUm - pos), 3 * kIntervalUm) << "true position " << pos;
        ASSERT_FALSE(m->candidates.empty());
        EXPECT_EQ(m->candidates.front().index, m->index);
        for (size_t k = 1; k < m->candidates.size(); ++k)
            EXPECT_GE(m->candidates[k - 1].score, m->candidates[k].score);
        // A window that excludes the truth still answers, inside the window.
        MatchOptions w;
        w.first = 35;
        w.last = 40;
        auto far = matchSection(*sec, stack, w);
        ASSERT_TRUE(far.ok());
        EXPECT_GE(far->index, 35);
        EXPECT_LT(far->score, m->score);
    }
}

// MatchOptions::alsoScore (docs/atlas.md, "The plan's slices are scored in the live match"): the
// slices the plan predicts are scored beside the overlap shortlist, so that a search whose
// shortlist misses them (the demo's s02 on the slowly changing built-in atlas) cannot place the
// section elsewhere for want of scoring them. With a shortlist of one slice, the asked slices are
// among the scored candidates; asked at the truth, the answer is no further from it than without
// them.
TEST(AtlasMatching, TheSlicesThePlanPredictsAreScoredBesideTheShortlist) {
    double workUm = 0;
    const auto stack = builtinStack(workUm);
    sim::GeneratorOptions go;
    go.seed = 5;
    go.imageSize = {900, 660};
    const double pos = 3300;
    auto gen = sim::generateSection(sim::builtinAtlasPlane(pos / kLengthUm), go);
    ASSERT_TRUE(gen.ok()) << gen.error().message;
    const auto& a = gen->truth.affineAtlasFromImage;
    const double imageUm = std::sqrt(std::abs(a(0, 0) * a(1, 1) - a(0, 1) * a(1, 0))) * kUmPerPx;
    auto sec = sectionFeatures(gen->image, imageUm, workUm);
    ASSERT_TRUE(sec.ok()) << sec.error().message;
    MatchOptions narrow;
    narrow.shortlist = 1;
    auto alone = matchSection(*sec, stack, narrow);
    ASSERT_TRUE(alone.ok()) << alone.error().message;
    const int truth = int(std::lround(pos / kIntervalUm));
    MatchOptions asked = narrow;
    asked.alsoScore = {truth - 1, truth, truth + 1, 1000}; // an index past the stack is ignored
    auto hinted = matchSection(*sec, stack, asked);
    ASSERT_TRUE(hinted.ok()) << hinted.error().message;
    for (const int s : {truth - 1, truth, truth + 1})
        EXPECT_TRUE(std::any_of(hinted->candidates.begin(), hinted->candidates.end(),
                                [&](const MatchCandidate& c) { return c.index == s; }))
            << "slice " << s << " was not scored";
    EXPECT_GE(hinted->score, alone->score);
    EXPECT_LE(std::abs(hinted->positionUm - pos), std::abs(alone->positionUm - pos) + 1e-6);
    EXPECT_LE(std::abs(hinted->positionUm - pos), kIntervalUm);
}

TEST(AtlasMatching, BadInputsAreErrors) {
    double workUm = 0;
    const auto stack = builtinStack(workUm);
    EXPECT_EQ(sectionFeatures(cv::Mat(), 10, workUm).error().code,
              core::ErrorCode::InvalidArgument);
    EXPECT_EQ(sectionFeatures(cv::Mat::zeros(400, 400, CV_16U), 10, workUm).error().code,
              core::ErrorCode::NoTissue);
    sim::GeneratorOptions go;
    go.imageSize = {600, 440};
    auto gen = sim::generateSection(sim::builtinAtlasPlane(0.5), go);
    ASSERT_TRUE(gen.ok());
    auto sec = sectionFeatures(gen->image, 0, workUm); // unknown pixel size works too
    ASSERT_TRUE(sec.ok()) << sec.error().message;
    EXPECT_EQ(matchSection(*sec, {}).error().code, core::ErrorCode::InvalidArgument);
    MatchOptions bad;
    bad.first = 30;
    bad.last = 50;
    EXPECT_EQ(matchSection(*sec, stack, bad).error().code, core::ErrorCode::InvalidArgument);
    // A stack with no brain at all.
    std::vector<SliceFeatures> empty{sliceFeatures(cv::Mat::zeros(50, 50, CV_32S), 25, 0, workUm)};
    EXPECT_EQ(matchSection(*sec, empty).error().code, core::ErrorCode::NoTissue);
}

TEST(AtlasMatching, SeriesModeKeepsTheCuttingOrder) {
    double workUm = 0;
    const auto stack = builtinStack(workUm);
    std::vector<SectionFeatures> sections;
    const std::vector<double> truth{1200, 2400, 3600, 4800, 6000};
    for (size_t k = 0; k < truth.size(); ++k) {
        sim::GeneratorOptions go;
        go.seed = 100 + k;
        go.imageSize = {600, 440};
        auto gen = sim::generateSection(sim::builtinAtlasPlane(truth[k] / kLengthUm), go);
        ASSERT_TRUE(gen.ok()) << gen.error().message;
        const auto& a = gen->truth.affineAtlasFromImage;
        const double imageUm =
            std::sqrt(std::abs(a(0, 0) * a(1, 1) - a(0, 1) * a(1, 0))) * kUmPerPx;
        auto sec = sectionFeatures(gen->image, imageUm, workUm);
        ASSERT_TRUE(sec.ok()) << sec.error().message;
        sections.push_back(std::move(*sec));
    }
    SeriesOptions o;
    o.minStep = 2;
    auto series = matchSeries(sections, stack, o);
    ASSERT_TRUE(series.ok()) << series.error().message;
    ASSERT_EQ(series->size(), truth.size());
    for (size_t k = 0; k < truth.size(); ++k) {
        EXPECT_LE(std::abs((*series)[k].positionUm - truth[k]), 3 * kIntervalUm) << k;
        if (k > 0) {
            EXPECT_GE((*series)[k].index - (*series)[k - 1].index, o.minStep) << k;
            EXPECT_GT((*series)[k].positionUm, (*series)[k - 1].positionUm) << k;
        }
    }
    // More sections than the stack can hold that far apart.
    o.minStep = 11;
    EXPECT_EQ(matchSeries(sections, stack, o).error().code, core::ErrorCode::InvalidArgument);
    EXPECT_TRUE(matchSeries({}, stack).ok());
}

// Live series matching: seven built-in sections 800 um apart with the fifth planned one lost.
// After three whole-stack searches each section is searched in a window around the model's
// prediction; the skip is reported and the spacing found.
TEST(SeriesMatching, WindowsFollowTheModelAndTheSkipIsReported) {
    double workUm = 0;
    const auto stack = builtinStack(workUm);
    const std::vector<double> truth{800, 1600, 2400, 3200, 4800, 5600, 6400};
    SeriesMatchOptions o;
    o.model.intervalUm = 800;
    SeriesMatcher matcher(stack, o);
    std::vector<SectionFeatures> sections;
    for (size_t k = 0; k < truth.size(); ++k) {
        sim::GeneratorOptions go;
        go.seed = 300 + k;
        go.imageSize = {600, 440};
        auto gen = sim::generateSection(sim::builtinAtlasPlane(truth[k] / kLengthUm), go);
        ASSERT_TRUE(gen.ok()) << gen.error().message;
        const auto& a = gen->truth.affineAtlasFromImage;
        const double imageUm =
            std::sqrt(std::abs(a(0, 0) * a(1, 1) - a(0, 1) * a(1, 0))) * kUmPerPx;
        auto sec = sectionFeatures(gen->image, imageUm, workUm);
        ASSERT_TRUE(sec.ok()) << sec.error().message;
        ASSERT_TRUE(matcher.add(*sec).ok());
        sections.push_back(std::move(*sec));
    }
    ASSERT_TRUE(matcher.finish(sections).ok());
    ASSERT_EQ(matcher.matches().size(), truth.size());
    for (size_t k = 0; k < truth.size(); ++k) {
        EXPECT_LE(std::abs(matcher.matches()[k].positionUm - truth[k]), 2 * kIntervalUm) << k;
        EXPECT_EQ(matcher.searches()[k].windowed, k >= 3) << k;
    }
    // The fourth section's window is centred on the prediction (3200 um) and holds the truth.
    const SeriesSearch& w = matcher.searches()[3];
    EXPECT_NEAR(w.predictedUm, 3200, 2 * kIntervalUm);
    EXPECT_LE(stack[size_t(w.first)].positionUm, 3200);
    EXPECT_GE(stack[size_t(w.last)].positionUm, 3200);
    EXPECT_NEAR(matcher.fit().spacingUm, 800, 120);
    EXPECT_EQ(matcher.fit().sections[4].anomaly, SeriesAnomaly::Skipped);
    EXPECT_EQ(matcher.fit().sections[4].missingBefore, 1);
    // finish() needs the same sections.
    sections.pop_back();
    EXPECT_EQ(matcher.finish(sections).error().code, core::ErrorCode::InvalidArgument);
}

// Real tissue: six consecutive sections of the gerbi series (15-20, RGB fluorescence, tile
// seams) matched live against a 100 um stack of the 50 um annotation with a 300 um plan. Their
// matches keep the cutting order, at most one is flagged, and the fitted spacing is within 15%
// of ABBA's 335.8 um. (The absolute positions are compared with ABBA's by slst_bench_series.)
TEST(SeriesMatching, RealGerbiSectionsFollowTheSeriesLine) {
    namespace fs = std::filesystem;
    const fs::path atlas = fs::path(SLST_SHARED_DIR) / "atlas" / "allen-ccf-2017";
    const fs::path gerbi = fs::path(SLST_SHARED_DIR) / "sections" / "abba-gerbi-series";
    if (!fs::exists(atlas / "annotation_50.nrrd") || !fs::exists(gerbi / "Section-15.jpg"))
        GTEST_SKIP() << "no Allen annotation or gerbi series under " << SLST_SHARED_DIR;
    double workUm = 0;
    std::string error;
    const std::vector<SliceFeatures> stack = allenStack100um(atlas, workUm, error);
    ASSERT_FALSE(stack.empty()) << error;
    // Thumbnail pixel sizes from sections.csv.
    const std::vector<double> umPerPx{10.401, 10.521, 10.838, 10.838, 10.534, 10.531};
    SeriesMatchOptions o;
    o.model.intervalUm = 300;
    SeriesMatcher matcher(stack, o);
    std::vector<SectionFeatures> sections;
    for (int n = 15; n <= 20; ++n) {
        auto image = core::readImage(gerbi / ("Section-" + std::to_string(n) + ".jpg"));
        ASSERT_TRUE(image.ok()) << image.error().message;
        auto sec = sectionFeatures(*image, umPerPx[size_t(n - 15)], workUm);
        ASSERT_TRUE(sec.ok()) << sec.error().message;
        ASSERT_TRUE(matcher.add(*sec).ok());
        sections.push_back(std::move(*sec));
    }
    ASSERT_TRUE(matcher.finish(sections).ok());
    const auto& m = matcher.matches();
    for (size_t k = 1; k < m.size(); ++k)
        EXPECT_GT(m[k].positionUm, m[k - 1].positionUm) << k;
    // Section 15 is matched about 150 um anterior of the line the others make (0.44 spacing):
    // off the line, as the full benchmark also reports it. The other five are regular.
    int regular = 0;
    for (size_t k = 0; k < m.size(); ++k)
        regular += matcher.fit().sections[k].anomaly == SeriesAnomaly::None;
    EXPECT_GE(regular, 5);
    EXPECT_NEAR(matcher.fit().spacingUm, 335.8, 0.15 * 335.8);
}

// The frontal levels (olfactory bulbs, frontal pole) are roundish: the outline fits nearly as
// well turned over. Every third slice tries both ways up and keeps the better overlap, the
// others take the way up of the best of those (the seed), so a slice near the truth could be
// aligned upside down, score nothing and leave the match to its neighbours. A plane of the Allen
// average template (real contrast) at 1800 um, cut with the series benchmark's tilt (LR 2,
// DV -1.5 degrees), 12.5 um per pixel, turned -13.3 degrees (slst_bench_series --data template,
// section 1, there matched 1922 um before and 1813 um after), with three noise draws: matched
// 1678, 1920 and 1678 um while slice 18 kept its own (upside down) alignment; within 80 um now
// that such a slice is also scored the seed's way up.
TEST(AtlasMatching, ASliceIsScoredTheSectionsWayUpOnRoundishLevels) {
    namespace fs = std::filesystem;
    const fs::path atlas = fs::path(SLST_SHARED_DIR) / "atlas" / "allen-ccf-2017";
    if (!fs::exists(atlas / "annotation_50.nrrd") ||
        !fs::exists(atlas / "average_template_100.nrrd"))
        GTEST_SKIP() << "no Allen annotation or average template under " << SLST_SHARED_DIR;
    double workUm = 0;
    std::string error;
    const std::vector<SliceFeatures> stack = allenStack100um(atlas, workUm, error);
    ASSERT_FALSE(stack.empty()) << error;
    auto tmpl = core::readNrrd(atlas / "average_template_100.nrrd");
    ASSERT_TRUE(tmpl.ok()) << tmpl.error().message;
    const double positionUm = 1800, turnDeg = -13.3;
    for (const std::uint64_t noiseSeed : {17, 18, 19}) {
        cv::RNG noiseRng(noiseSeed);
        auto g = planeGeometry(*tmpl, VolumeAxes::Allen,
                               {PlaneOrientation::Coronal, positionUm, 2.0, -1.5, 50});
        ASSERT_TRUE(g.ok()) << g.error().message;
        auto plane = sampleLabels(*tmpl, VolumeAxes::Allen, *g);
        ASSERT_TRUE(plane.ok()) << plane.error().message;
        cv::Mat f, big, turned, image;
        plane->convertTo(f, CV_32F);
        double lo = 0, hi = 0;
        cv::minMaxLoc(f, &lo, &hi);
        cv::resize(f, big, {}, 4, 4, cv::INTER_CUBIC); // 12.5 um per pixel
        const int side = int(std::max(big.cols, big.rows) * 1.2);
        cv::Mat rot =
            cv::getRotationMatrix2D({float(big.cols) / 2, float(big.rows) / 2}, turnDeg, 1);
        rot.at<double>(0, 2) += (side - big.cols) / 2.0;
        rot.at<double>(1, 2) += (side - big.rows) / 2.0;
        cv::warpAffine(big, turned, rot, {side, side}, cv::INTER_LINEAR, cv::BORDER_CONSTANT, 0);
        cv::Mat noise(turned.size(), CV_32F);
        noiseRng.fill(noise, cv::RNG::NORMAL, 0, 0.03 * hi);
        turned += noise;
        turned.convertTo(image, CV_8U, 255.0 / std::max(hi, 1.0));
        auto sec = sectionFeatures(image, 12.5, workUm);
        ASSERT_TRUE(sec.ok()) << sec.error().message;
        auto m = matchSection(*sec, stack);
        ASSERT_TRUE(m.ok()) << m.error().message;
        EXPECT_NEAR(m->positionUm, positionUm, 80) << "noise seed " << noiseSeed;
    }
}

// The gerbi series' one order breaker: section 21 matches 8189 um on its own, behind section 20
// (8337 um; ABBA puts 21 about 340 um after 20) with a score like its neighbours', so no score
// rule can tell it is wrong. Matched live as the whole series (25 sections, 300 um plan, as
// slst_bench_series does), the Viterbi pass at the end of finish()
// (SeriesMatchOptions::orderWeight) moves it between its neighbours and the series comes out in
// order; with orderWeight 0 (the code before the pass) the same run leaves 21 behind 20.
// Sections 17-23 alone do not show it (21 is then matched right on its own).
TEST(SeriesMatching, TheSeriesPassPutsTheGerbiSeriesInOrder) {
    namespace fs = std::filesystem;
    const fs::path atlas = fs::path(SLST_SHARED_DIR) / "atlas" / "allen-ccf-2017";
    const fs::path gerbi = fs::path(SLST_SHARED_DIR) / "sections" / "abba-gerbi-series";
    if (!fs::exists(atlas / "annotation_50.nrrd") || !fs::exists(gerbi / "sections.csv"))
        GTEST_SKIP() << "no Allen annotation or gerbi series under " << SLST_SHARED_DIR;
    double workUm = 0;
    std::string error;
    const std::vector<SliceFeatures> stack = allenStack100um(atlas, workUm, error);
    ASSERT_FALSE(stack.empty()) << error;
    // sections.csv: section,file,width_px,height_px,um_per_px,...
    std::ifstream csv(gerbi / "sections.csv");
    std::string line;
    std::getline(csv, line);
    std::vector<SectionFeatures> sections;
    while (std::getline(csv, line)) {
        std::stringstream ss(line);
        std::vector<std::string> f;
        for (std::string c; std::getline(ss, c, ',');)
            f.push_back(c);
        ASSERT_GE(f.size(), 5u) << line;
        auto image = core::readImage(gerbi / f[1]);
        ASSERT_TRUE(image.ok()) << image.error().message;
        auto sec = sectionFeatures(*image, std::stod(f[4]), workUm);
        ASSERT_TRUE(sec.ok()) << sec.error().message;
        sections.push_back(std::move(*sec));
    }
    ASSERT_EQ(sections.size(), 25u);
    auto run = [&](double orderWeight) {
        SeriesMatchOptions o;
        o.model.intervalUm = 300;
        o.orderWeight = orderWeight;
        SeriesMatcher matcher(stack, o);
        for (const SectionFeatures& sec : sections)
            EXPECT_TRUE(matcher.add(sec).ok());
        EXPECT_TRUE(matcher.finish(sections).ok());
        std::vector<double> positions;
        for (const SeriesSectionFit& f : matcher.fit().sections)
            positions.push_back(f.positionUm);
        return positions;
    };
    const std::vector<double> before = run(0);
    ASSERT_EQ(before.size(), 25u);
    EXPECT_LT(before[20], before[19]) << "without the pass section 21 lay behind 20";
    const std::vector<double> after = run(SeriesMatchOptions{}.orderWeight);
    ASSERT_EQ(after.size(), 25u);
    for (size_t k = 1; k < after.size(); ++k)
        EXPECT_GT(after[k], after[k - 1]) << "section " << k + 1;
}
