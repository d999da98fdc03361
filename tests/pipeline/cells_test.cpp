// Cells per region (pipeline/cells.hpp): the detector on synthetic blobs, clusters, channels,
// polarity; the count through a known registration with damage; the ontology roll-up.
#include "slicestation/pipeline/cells.hpp"
#include "slicestation/sim/section_generator_b.hpp"

#include <gtest/gtest.h>

#include <iostream>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <map>
#include <random>

using namespace slicestation;
using namespace slicestation::pipeline;

namespace {

/// Gaussian blobs (FWHM `diameter`) of `amplitude` on a background with a gradient and noise.
cv::Mat blobs(cv::Size size, const std::vector<cv::Point2d>& centres, double diameter,
              double amplitude, double noise, std::uint64_t seed) {
    cv::Mat img(size, CV_32F);
    for (int y = 0; y < size.height; ++y)
        for (int x = 0; x < size.width; ++x)
            img.at<float>(y, x) = float(100 + 40.0 * x / size.width + 20.0 * y / size.height);
    const double s = diameter / 2.3548;
    for (const auto& c : centres)
        for (int y = std::max(0, int(c.y) - 12); y < std::min(size.height, int(c.y) + 13); ++y)
            for (int x = std::max(0, int(c.x) - 12); x < std::min(size.width, int(c.x) + 13); ++x)
                img.at<float>(y, x) +=
                    float(amplitude *
                          std::exp(-((x - c.x) * (x - c.x) + (y - c.y) * (y - c.y)) / (2 * s * s)));
    cv::Mat n(size, CV_32F);
    cv::RNG rng(seed);
    rng.fill(n, cv::RNG::NORMAL, 0, noise);
    img += n;
    cv::Mat out;
    img.convertTo(out, CV_16U);
    return out;
}

/// `count` centres at least `minDist` apart, `margin` from the border.
std::vector<cv::Point2d> spread(cv::Size size, int count, double minDist, std::uint64_t seed) {
    std::mt19937_64 g(seed);
    std::uniform_real_distribution<double> ux(15, size.width - 15), uy(15, size.height - 15);
    std::vector<cv::Point2d> out;
    for (int tries = 0; int(out.size()) < count && tries < 100000; ++tries) {
        const cv::Point2d p(ux(g), uy(g));
        bool ok = true;
        for (const auto& q : out)
            ok = ok && cv::norm(p - q) >= minDist;
        if (ok)
            out.push_back(p);
    }
    return out;
}

int matched(const std::vector<DetectedCell>& found, const std::vector<cv::Point2d>& truth,
            double radius) {
    int n = 0;
    for (const auto& t : truth)
        for (const auto& f : found)
            if (cv::norm(f.imagePx - t) <= radius) {
                ++n;
                break;
            }
    return n;
}

} // namespace

TEST(CellDetector, FindsEveryIsolatedBlobOnAGradientWithNoise) {
    const cv::Size size(600, 450);
    const auto truth = spread(size, 250, 14, 3);
    ASSERT_EQ(truth.size(), 250u);
    const cv::Mat img = blobs(size, truth, 6, 60, 4, 7);
    CellDetectorOptions o;
    o.diameterPx = 6;
    auto found = detectCells(img, o);
    ASSERT_TRUE(found.ok()) << found.error().message;
    // 98% within a pixel: the gcc build finds 249 (all matched), the clang sanitizer build 246
    // (all matched) on this same image; which blobs near the threshold pass differs by build.
    EXPECT_NEAR(double(found->size()), 250.0, 5.0);
    EXPECT_GE(matched(*found, truth, 1.0), 245); // centres within a pixel
}

namespace {

/// 60 single cells and 30 touching pairs, centres `apart` x the diameter (8 px) apart.
std::vector<cv::Point2d> pairs(double apart) {
    std::vector<cv::Point2d> truth;
    const auto seeds = spread({600, 450}, 90, 30, 11);
    for (size_t i = 0; i < seeds.size(); ++i) {
        truth.push_back(seeds[i]);
        if (i % 3 == 0)
            truth.push_back(seeds[i] + cv::Point2d(apart * 8, 0));
    }
    return truth;
}

} // namespace

TEST(CellDetector, SplitsTouchingPairsLoGByShapeThresholdByMedianArea) {
    const cv::Size size(600, 450);
    // LoG: pairs whose blobs (FWHM = diameter) touch at 1.2 diameters apart keep two maxima.
    // Closer Gaussian blobs (0.9 diameters) merge into one maximum: docs/cells.md.
    std::vector<cv::Point2d> truth = pairs(1.2);
    ASSERT_EQ(truth.size(), 120u);
    CellDetectorOptions o;
    o.diameterPx = 8;
    auto log = detectCells(blobs(size, truth, 8, 80, 3, 5), o);
    ASSERT_TRUE(log.ok());
    EXPECT_NEAR(double(log->size()), double(truth.size()), 3.0);
    EXPECT_GE(matched(*log, truth, 1.5), int(truth.size()) - 3);

    // The paper's rule splits merged pairs (0.9 diameters apart) by the median cluster area.
    truth = pairs(0.9);
    const cv::Mat img = blobs(size, truth, 8, 80, 3, 5);

    o.method = CellMethod::Threshold;
    auto thr = detectCells(img, o);
    ASSERT_TRUE(thr.ok());
    int cells = 0, clusters = 0;
    for (const auto& c : *thr) {
        cells += c.clusterCells;
        clusters += c.clusterCells > 1;
    }
    EXPECT_NEAR(double(cells), double(truth.size()), 6.0);
    EXPECT_GE(clusters, 25); // the pairs were split by area
}

TEST(CellDetector, LoGSplitsPairsThatGaveOneMaximumByArea) {
    // 0.8 diameters apart (the generator's closest cells): one LoG maximum per pair. Without the
    // split a pair is one cell; with it (splitAt, docs/cells.md) both are found near their centres.
    const cv::Size size(600, 450);
    const std::vector<cv::Point2d> truth = pairs(0.8);
    ASSERT_EQ(truth.size(), 120u);
    const cv::Mat img = blobs(size, truth, 8, 80, 3, 5);
    CellDetectorOptions o;
    o.diameterPx = 8;
    o.splitAt = 0;
    auto whole = detectCells(img, o);
    ASSERT_TRUE(whole.ok());
    std::cout << "no split: " << whole->size() << " for " << truth.size() << "\n";
    EXPECT_LT(double(whole->size()), 0.9 * double(truth.size())) << "pairs merge without it";
    o.splitAt = 1.5;
    auto split = detectCells(img, o);
    ASSERT_TRUE(split.ok());
    std::cout << "split: " << split->size() << ", " << matched(*split, truth, 3.0)
              << " within 3 px of a true centre\n";
    EXPECT_NEAR(double(split->size()), double(truth.size()), 8.0);
    EXPECT_GE(matched(*split, truth, 3.0), int(truth.size()) - 12);
    o.splitAt = 0.5;
    EXPECT_FALSE(detectCells(img, o).ok()) << "splitAt is 0 or in [1, 2]";
}

TEST(CellDetector, DarkCellsOnBrightGlassAndTheChosenChannel) {
    const cv::Size size(500, 400);
    const auto truth = spread(size, 120, 14, 21);
    cv::Mat bright = blobs(size, truth, 6, 60, 3, 9);
    // Brightfield: glass bright, tissue (the middle) a little darker, cells dark.
    cv::Mat dark;
    bright.convertTo(dark, CV_32F);
    dark = 400.0 - dark;
    cv::Mat dark16;
    dark.convertTo(dark16, CV_16U);
    CellDetectorOptions o;
    o.diameterPx = 6;
    auto found = detectCells(dark16, o); // Auto: the border is the brightest
    ASSERT_TRUE(found.ok());
    EXPECT_NEAR(double(found->size()), 120.0, 3.0);

    // Colour: cells only in the red plane (OpenCV's index 2); channel 0 is red in file order.
    cv::Mat b8;
    bright.convertTo(b8, CV_8U, 1.0 / 2);
    const cv::Mat flat(size, CV_8U, cv::Scalar(60));
    cv::Mat bgr;
    cv::merge(std::vector<cv::Mat>{flat, flat, b8}, bgr);
    o.channel = 0;
    auto red = detectCells(bgr, o);
    ASSERT_TRUE(red.ok());
    EXPECT_NEAR(double(red->size()), 120.0, 3.0);
    o.channel = 1;
    auto green = detectCells(bgr, o);
    ASSERT_TRUE(green.ok());
    EXPECT_LE(green->size(), 2u);
}

// A labelled cell clipped at the sensor's ceiling on a bright, densely textured stain (a Nissl
// counterstain under a strong label) answers the LoG with the clipped height alone, which the
// texture matches; the clipped disc of a cell's size still tells it from texture, which clips
// in specks. The same pixels as float (no ceiling known) show what the LoG alone finds.
TEST(CellDetector, CellsClippedOnABrightTexturedStainAreFound) {
    const cv::Size size(480, 480);
    const double diameter = 6;
    cv::Mat img(size, CV_32F);
    cv::RNG rng(17);
    rng.fill(img, cv::RNG::UNIFORM, 0, 1);
    // Texture: specks of about 2 px over a bright level, heavy-tailed like a dense Nissl stain.
    cv::pow(img, 6, img);
    img = 38000 + 60000 * img;
    cv::GaussianBlur(img, img, cv::Size(), 0.8);
    const auto centres = spread(size, 60, 4 * diameter, 5);
    const double s = diameter / 2.3548;
    for (const auto& c : centres)
        for (int y = int(c.y) - 12; y <= int(c.y) + 12; ++y)
            for (int x = int(c.x) - 12; x <= int(c.x) + 12; ++x)
                img.at<float>(y, x) +=
                    float(90000 *
                          std::exp(-((x - c.x) * (x - c.x) + (y - c.y) * (y - c.y)) / (2 * s * s)));
    cv::Mat sensor;
    img.convertTo(sensor, CV_16U); // saturates at 65535: the cells clip
    CellDetectorOptions o;
    o.diameterPx = diameter;
    o.polarity = CellPolarity::Bright;
    auto clippedKnown = detectCells(sensor, o);
    cv::Mat asFloat;
    sensor.convertTo(asFloat, CV_32F);
    auto logAlone = detectCells(asFloat, o);
    ASSERT_TRUE(clippedKnown && logAlone);
    const int found = matched(*clippedKnown, centres, 0.6 * diameter);
    const int foundByLoG = matched(*logAlone, centres, 0.6 * diameter);
    std::cout << "[ clipped  ] " << centres.size() << " cells: LoG alone " << foundByLoG << " of "
              << logAlone->size() << " detections, with the clipped pieces " << found << " of "
              << clippedKnown->size() << "\n";
    EXPECT_GE(found, int(0.95 * double(centres.size())));
    EXPECT_GE(found, int(0.9 * double(clippedKnown->size())))
        << "texture clipped in specks counted";
    EXPECT_LT(foundByLoG, found) << "the case needs the clipped pieces";
}

namespace {

/// A plane of atlas labels: an elliptic brain of eight regions (four sectors in two rings), ids
/// 101-108 in a 456 x 320 plane (the size of a 25 um coronal CCF plane).
cv::Mat eightRegionPlane() {
    cv::Mat labels(320, 456, CV_32S, cv::Scalar(0));
    const cv::Point2d c(228, 160);
    for (int y = 0; y < labels.rows; ++y)
        for (int x = 0; x < labels.cols; ++x) {
            const double u = (x - c.x) / 200, v = (y - c.y) / 140, r = std::hypot(u, v);
            if (r > 1)
                continue;
            const int sector = int(std::floor((std::atan2(v, u) + CV_PI) / (CV_PI / 2))) % 4;
            labels.at<std::int32_t>(y, x) = 101 + sector + (r > 0.6 ? 4 : 0);
        }
    return labels;
}

} // namespace

// Ground truth on generated Nissl sections (the second generator family's Nissl stain: every
// cell body stained, dense and touching, its level following each region's cell density; the
// labelled cells painted over it in the same channel, clipped at the 16-bit ceiling), counted
// through the true labels, so the error is the detector's alone. The clipped cores with the
// cell's shoulder (addClippedCells) bring the under-count down; issue 22's 5% is not reached
// here: measured, the median per-region error of these four sections (20 regions of >= 100
// true cells) went from 18.3% to 11.8%, regions within 5% from 3 to 4, all still under-counted
// (touching clipped cells with one core, docs/cells.md).
TEST(CellGroundTruth, AGeneratedNisslSectionIsCountedPerRegionWithSmallerError) {
    const cv::Mat labels = eightRegionPlane();
    std::vector<double> errors;
    for (const std::uint64_t seed : {2, 11, 18, 21}) {
        sim::GeneratorOptionsB g;
        g.seed = seed;
        g.stain = sim::StainB::Nissl;
        g.cells.enabled = true;
        g.fiberTractIds = {};
        g.ventricleIds = {};
        auto gen = sim::generateSectionB(labels, core::Ontology{}, g);
        ASSERT_TRUE(gen.ok()) << gen.error().message;
        CellDetectorOptions o;
        o.diameterPx = g.cells.diameterPx;
        o.mask = gen->truth.tissueMask.clone();
        auto found = detectCells(gen->image, o);
        ASSERT_TRUE(found.ok()) << found.error().message;
        std::map<std::int32_t, int> truth, measured;
        for (const auto& c : gen->cells)
            if (c.counted && c.atlasId > 0)
                ++truth[c.atlasId];
        for (const auto& c : *found) {
            const cv::Point p(int(std::lround(c.imagePx.x)), int(std::lround(c.imagePx.y)));
            const std::int32_t id = gen->truth.labelsInImage.at<std::int32_t>(p);
            if (id > 0)
                ++measured[id];
        }
        for (const auto& [id, n] : truth) {
            if (n < 100)
                continue;
            const double err = 100.0 * (measured[id] - n) / n;
            errors.push_back(std::abs(err));
            std::cout << "[ nissl    ] seed " << seed << " region " << id << ": " << n << " true, "
                      << measured[id] << " counted (" << err << "%)\n";
        }
    }
    ASSERT_GE(errors.size(), 12u);
    std::sort(errors.begin(), errors.end());
    const double med = errors[errors.size() / 2];
    const auto within =
        std::count_if(errors.begin(), errors.end(), [](double e) { return e <= 5; });
    std::cout << "[ nissl    ] median per-region error " << med << "%, " << within << " of "
              << errors.size() << " regions within 5%\n";
    // Measured: 11.8% (gcc build), 13.3% (CI's clang-14 sanitizer build); 18.3% before the
    // clipped cores, which this bound still fails.
    EXPECT_LE(med, 15.0) << "before the clipped cores: 18.3%";
}

TEST(CellDetector, BadInputIsAnError) {
    const cv::Mat img(100, 100, CV_8U, cv::Scalar(0));
    CellDetectorOptions o;
    o.channel = 1;
    auto r = detectCells(img, o);
    ASSERT_FALSE(r.ok());
    EXPECT_EQ(r.error().code, core::ErrorCode::InvalidArgument);
    EXPECT_NE(r.error().message.find("channel 1"), std::string::npos) << r.error().message;
    o = {};
    o.diameterPx = 1;
    EXPECT_FALSE(detectCells(img, o).ok());
    o = {};
    o.mask = cv::Mat(50, 50, CV_8U);
    EXPECT_FALSE(detectCells(img, o).ok());
    EXPECT_FALSE(detectCells(cv::Mat(), {}).ok());
}

namespace {

core::Ontology smallOntology() {
    // root 997 -> grey 8 -> {CTX 688 -> {MO 500}, TH 549}; fiber tracts 1009 under root.
    std::vector<core::Structure> s{{997, 0, "root", "root", {997}, 0},
                                   {8, 997, "Grey", "grey", {997, 8}, 0},
                                   {688, 8, "Cortex", "CTX", {997, 8, 688}, 0},
                                   {500, 688, "Motor", "MO", {997, 8, 688, 500}, 0},
                                   {549, 8, "Thalamus", "TH", {997, 8, 549}, 0},
                                   {1009, 997, "fiber tracts", "fiber tracts", {997, 1009}, 0}};
    auto o = core::Ontology::create(std::move(s));
    EXPECT_TRUE(o.ok());
    return std::move(*o);
}

} // namespace

TEST(CellCounts, RollUpSumsEveryAncestorAndKeepsUnknownIds) {
    const core::Ontology onto = smallOntology();
    std::vector<RegionCount> leaves{
        {500, 0, 0, 10, 100}, {549, 0, 0, 5, 50}, {1009, 0, 0, 1, 20}, {4242, 0, 0, 2, 7}};
    const auto rows = rollUp(leaves, onto);
    auto find = [&](std::uint32_t id) {
        for (const auto& r : rows)
            if (r.id == id)
                return r;
        ADD_FAILURE() << "no row " << id;
        return RegionCount{};
    };
    EXPECT_EQ(find(997).cells, 16);
    EXPECT_DOUBLE_EQ(find(997).areaPx, 170);
    EXPECT_EQ(find(8).cells, 15);
    EXPECT_EQ(find(688).cells, 10);
    EXPECT_EQ(find(688).parentId, 8u);
    EXPECT_EQ(find(500).depth, 3);
    EXPECT_EQ(find(4242).cells, 2);
    EXPECT_EQ(find(4242).parentId, 0u);
    EXPECT_EQ(rows.front().id, 997u); // ontology order, unknown ids last
    EXPECT_EQ(rows.back().id, 4242u);
}

TEST(CellCounts, MapsThroughTheRegistrationAndLeavesDamageOutOfCountsAndAreas) {
    // Atlas: left half MO (500), right half TH (549), a border of 0. Identity registration at
    // working scale 0.5 of a 400 x 300 section.
    cv::Mat labels(300, 400, CV_32S, cv::Scalar(0));
    labels(cv::Rect(20, 20, 180, 260)).setTo(500);
    labels(cv::Rect(200, 20, 180, 260)).setTo(549);
    Registration reg;
    reg.imageSize = {400, 300};
    reg.workingScale = 0.5;
    // working px w = 0.5 (x + 0.5) - 0.5; atlas = image: x = 2 w + 0.5.
    reg.atlasFromWorking = cv::Matx23d(2, 0, 0.5, 0, 2, 0.5);
    reg.workingGrey = cv::Mat(150, 200, CV_32F, cv::Scalar(0.5));
    reg.workingTissueMask = cv::Mat(150, 200, CV_8U, cv::Scalar(0));
    reg.workingTissueMask(cv::Rect(10, 10, 180, 130)).setTo(255);
    // Damage: a square on the right half, section px (300..340) x (100..140).
    DamageRegion d;
    d.polygon = {{300, 100}, {340, 100}, {340, 140}, {300, 140}};
    reg.damage.push_back(d);
    std::vector<DetectedCell> cells;
    for (int i = 0; i < 7; ++i)
        cells.push_back({{60.0 + 10 * i, 150}, 10, 1}); // MO
    for (int i = 0; i < 4; ++i)
        cells.push_back({{240.0 + 10 * i, 60}, 10, 1}); // TH
    cells.push_back({{320, 120}, 10, 2});               // TH, in damage: a cluster of 2
    cells.push_back({{5, 5}, 10, 1});                   // outside the brain
    auto t = countCells(reg, labels, cells, smallOntology());
    ASSERT_TRUE(t.ok()) << t.error().message;
    std::map<std::uint32_t, RegionCount> by;
    for (const auto& r : t->regions)
        by[r.id] = r;
    EXPECT_EQ(by[500].cells, 7);
    EXPECT_EQ(by[549].cells, 4);
    EXPECT_EQ(by[8].cells, 11);
    EXPECT_EQ(by[997].cells, 11);
    EXPECT_EQ(t->excludedCells, 2);
    EXPECT_EQ(t->cells.back().atlasId, 0);
    // Areas in section px: tissue is section (20..380) x (20..280) = 360 x 260; MO covers its
    // x < 200 part (180 x 260), TH the rest minus the 40 x 40 damage.
    EXPECT_NEAR(by[500].areaPx, 180.0 * 260, 4 * 260.0);
    EXPECT_NEAR(by[549].areaPx, 180.0 * 260 - 1600, 4 * 260.0);
    EXPECT_NEAR(t->excludedAreaPx, 1600, 200);
    EXPECT_NEAR(by[997].areaPx, by[500].areaPx + by[549].areaPx, 1e-6);
}

TEST(CellCounts, RefusesLabelsOfTheWrongTypeAndAnEmptyRegistration) {
    Registration reg;
    auto r = countCells(reg, cv::Mat(10, 10, CV_32S, cv::Scalar(1)), {}, {});
    ASSERT_FALSE(r.ok());
    EXPECT_EQ(r.error().code, core::ErrorCode::InvalidArgument);
    EXPECT_FALSE(countCells(reg, cv::Mat(10, 10, CV_8U), {}, {}).ok());
}
