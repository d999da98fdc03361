// Tile planning and stitching: tiles cut from a known image at known positions, reported with
// a stage position error, stitched and compared with the original.
#include "slicestation/pipeline/tile_stitching.hpp"

#include <gtest/gtest.h>

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <cmath>

namespace slicestation::test {
namespace {

using core::ErrorCode;

constexpr double kUmPerPx = 2.0;

/// Smooth random texture with a gradient: every overlap has structure to correlate.
cv::Mat texture(cv::Size size, int type, std::uint64_t seed) {
    cv::Mat noise(size, CV_32F);
    cv::RNG rng(seed);
    rng.fill(noise, cv::RNG::UNIFORM, 0.0, 1.0);
    cv::GaussianBlur(noise, noise, cv::Size(), 2.0);
    cv::normalize(noise, noise, 0.1, 0.9, cv::NORM_MINMAX);
    const double full = CV_MAT_DEPTH(type) == CV_16U ? 65535.0 : 255.0;
    cv::Mat out;
    noise.convertTo(out, CV_MAKETYPE(CV_MAT_DEPTH(type), 1), full);
    if (CV_MAT_CN(type) == 3) {
        cv::Mat shifted;
        cv::flip(out, shifted, 1);
        std::vector<cv::Mat> planes{out, shifted, 255 - out};
        cv::merge(planes, out);
    }
    return out;
}

struct Cut {
    std::vector<pipeline::Tile> tiles;
    cv::Point firstTopLeftPx; ///< where the mosaic's top-left should be in the original
};

/// Cuts `fieldPx` tiles from `image` at the plan's centres (snapped to whole pixels), and
/// reports each with a stage error of up to `errorPx` pixels.
Cut cutTiles(const cv::Mat& image, cv::Size fieldPx, double overlap, double errorPx,
             std::uint64_t seed) {
    const hw::StagePosition centre{image.cols * kUmPerPx / 2, image.rows * kUmPerPx / 2, 100};
    const double marginPx = 8; // keep every cut inside the image
    const auto plan = pipeline::planTiles(
        centre, (image.cols - 2 * marginPx) * kUmPerPx, (image.rows - 2 * marginPx) * kUmPerPx,
        fieldPx.width * kUmPerPx, fieldPx.height * kUmPerPx, overlap);
    cv::RNG rng(seed);
    Cut cut;
    cut.firstTopLeftPx = {INT32_MAX, INT32_MAX};
    for (const auto& c : plan.centres) {
        const cv::Point tl(static_cast<int>(std::lround(c.xUm / kUmPerPx - fieldPx.width / 2.0)),
                           static_cast<int>(std::lround(c.yUm / kUmPerPx - fieldPx.height / 2.0)));
        pipeline::Tile t;
        t.image = image(cv::Rect(tl, fieldPx)).clone();
        t.stage.xUm = (tl.x + fieldPx.width / 2.0 + rng.uniform(-errorPx, errorPx)) * kUmPerPx;
        t.stage.yUm = (tl.y + fieldPx.height / 2.0 + rng.uniform(-errorPx, errorPx)) * kUmPerPx;
        t.stage.zUm = c.zUm;
        cut.tiles.push_back(std::move(t));
        cut.firstTopLeftPx.x = std::min(cut.firstTopLeftPx.x, tl.x);
        cut.firstTopLeftPx.y = std::min(cut.firstTopLeftPx.y, tl.y);
    }
    return cut;
}

TEST(PlanTiles, OneTileWhenItFits) {
    const auto plan = pipeline::planTiles({1000, 2000, 50}, 500, 400, 640, 480);
    ASSERT_EQ(plan.centres.size(), 1u);
    EXPECT_EQ(plan.columns, 1);
    EXPECT_EQ(plan.rows, 1);
    EXPECT_EQ(plan.centres[0].xUm, 1000);
    EXPECT_EQ(plan.centres[0].yUm, 2000);
    EXPECT_EQ(plan.centres[0].zUm, 50);
}

TEST(PlanTiles, RowMajorOverlappingCoverage) {
    const double fw = 640, fh = 480, overlap = 0.1;
    const auto plan = pipeline::planTiles({10'000, 5'000, 7}, 1'700, 1'000, fw, fh, overlap);
    ASSERT_EQ(plan.columns, 3); // (1700 - 640) / 576 -> 2 steps
    ASSERT_EQ(plan.rows, 3);    // (1000 - 480) / 432 -> 2 steps
    ASSERT_EQ(plan.centres.size(), 9u);
    // Row-major: x varies fastest.
    EXPECT_LT(plan.centres[0].xUm, plan.centres[1].xUm);
    EXPECT_EQ(plan.centres[0].yUm, plan.centres[2].yUm);
    EXPECT_LT(plan.centres[2].yUm, plan.centres[3].yUm);
    // Covers the region exactly at its edges, overlap at least as asked.
    EXPECT_DOUBLE_EQ(plan.centres.front().xUm - fw / 2, 10'000 - 850);
    EXPECT_DOUBLE_EQ(plan.centres.back().xUm + fw / 2, 10'000 + 850);
    EXPECT_DOUBLE_EQ(plan.centres.front().yUm - fh / 2, 5'000 - 500);
    EXPECT_DOUBLE_EQ(plan.centres.back().yUm + fh / 2, 5'000 + 500);
    EXPECT_LE(plan.centres[1].xUm - plan.centres[0].xUm, fw * (1 - overlap) + 1e-9);
    EXPECT_LE(plan.centres[3].yUm - plan.centres[0].yUm, fh * (1 - overlap) + 1e-9);
    for (const auto& c : plan.centres)
        EXPECT_EQ(c.zUm, 7);
}

TEST(PlanTiles, InvalidInputGivesAnEmptyPlan) {
    EXPECT_TRUE(pipeline::planTiles({}, 1000, 1000, 0, 480).centres.empty());
    EXPECT_TRUE(pipeline::planTiles({}, 1000, 1000, 640, -1).centres.empty());
    EXPECT_TRUE(pipeline::planTiles({}, -5, 1000, 640, 480).centres.empty());
    EXPECT_TRUE(pipeline::planTiles({}, NAN, 1000, 640, 480).centres.empty());
    EXPECT_TRUE(pipeline::planTiles({}, 1000, 1000, 640, 480, 0.95).centres.empty());
    EXPECT_TRUE(pipeline::planTiles({}, 1000, 1000, 640, 480, -0.1).centres.empty());
}

struct StitchCase {
    int type;
    double errorPx;
};

class Stitch : public ::testing::TestWithParam<StitchCase> {};

TEST_P(Stitch, RecoversTheOriginalWithoutSeams) {
    const auto [type, errorPx] = GetParam();
    const cv::Mat original = texture({700, 520}, type, 3);
    const Cut cut = cutTiles(original, {256, 192}, 0.15, errorPx, 9);
    ASSERT_GE(cut.tiles.size(), 9u);
    auto mosaic = pipeline::stitchTiles(cut.tiles, kUmPerPx);
    ASSERT_TRUE(mosaic) << mosaic.error().message;
    ASSERT_EQ(mosaic->type(), type);
    const cv::Mat truth = original(cv::Rect(cut.firstTopLeftPx, mosaic->size()));
    cv::Mat diff;
    cv::absdiff(*mosaic, truth, diff);
    double maxDiff = 0;
    cv::minMaxLoc(diff.reshape(1), nullptr, &maxDiff);
    // Correctly placed tiles blend identical pixels: at most a rounding step anywhere, so no
    // seam anywhere.
    EXPECT_LE(maxDiff, 1.0);
    RecordProperty("max_abs_error", std::to_string(maxDiff));
}

INSTANTIATE_TEST_SUITE_P(TypesAndErrors, Stitch,
                         ::testing::Values(StitchCase{CV_16UC1, 0.0}, StitchCase{CV_16UC1, 3.0},
                                           StitchCase{CV_8UC1, 4.0}, StitchCase{CV_8UC3, 3.0}));

TEST(Stitch, WithoutRefinementStageErrorsShowAsSeams) {
    const cv::Mat original = texture({700, 520}, CV_16UC1, 3);
    const Cut cut = cutTiles(original, {256, 192}, 0.15, 3.0, 9);
    auto placedOnly = pipeline::stitchTiles(cut.tiles, kUmPerPx, false);
    auto refined = pipeline::stitchTiles(cut.tiles, kUmPerPx, true);
    ASSERT_TRUE(placedOnly && refined);
    // The placement-only mosaic mixes misplaced content: far larger errors than the refined one.
    const cv::Size common(std::min(placedOnly->cols, refined->cols),
                          std::min(placedOnly->rows, refined->rows));
    const cv::Rect r(cv::Point(16, 16), common - cv::Size(32, 32));
    const double refinedError =
        cv::norm((*refined)(r), original(r + cut.firstTopLeftPx), cv::NORM_L1);
    const double placedError =
        cv::norm((*placedOnly)(r), original(r + cut.firstTopLeftPx), cv::NORM_L1);
    EXPECT_GT(placedError, 20 * (refinedError + 1));
}

TEST(Stitch, BlankOverlapsKeepTheStagePlacement) {
    // Uniform glass: nothing to correlate; the tiles stay where the stage put them.
    const cv::Mat glass(400, 600, CV_16UC1, cv::Scalar(1000));
    const Cut cut = cutTiles(glass, {256, 192}, 0.15, 0.0, 1);
    auto mosaic = pipeline::stitchTiles(cut.tiles, kUmPerPx);
    ASSERT_TRUE(mosaic) << mosaic.error().message;
    EXPECT_EQ(cv::norm(*mosaic, cv::Mat(mosaic->size(), CV_16UC1, cv::Scalar(1000)), cv::NORM_INF),
              0.0);
}

TEST(Stitch, OneTileComesBackAsIs) {
    const cv::Mat image = texture({64, 48}, CV_8UC3, 2);
    auto mosaic = pipeline::stitchTiles({{image, {500, 500, 0}}}, kUmPerPx);
    ASSERT_TRUE(mosaic);
    EXPECT_EQ(cv::norm(*mosaic, image, cv::NORM_INF), 0.0);
}

TEST(Stitch, InvalidInput) {
    const cv::Mat a = texture({64, 48}, CV_8UC1, 1);
    const auto expectInvalid = [](const core::Result<cv::Mat>& r, const char* why) {
        ASSERT_FALSE(r) << why;
        EXPECT_EQ(r.error().code, ErrorCode::InvalidArgument) << why;
    };
    expectInvalid(pipeline::stitchTiles({}, kUmPerPx), "no tiles");
    expectInvalid(pipeline::stitchTiles({{a, {}}}, 0), "pixel size");
    expectInvalid(pipeline::stitchTiles({{a, {}}, {cv::Mat(), {}}}, kUmPerPx), "empty tile");
    expectInvalid(pipeline::stitchTiles({{a, {}}, {texture({64, 48}, CV_16UC1, 1), {}}}, kUmPerPx),
                  "mixed types");
    expectInvalid(pipeline::stitchTiles({{cv::Mat(4, 4, CV_64FC1, 0.0), {}}}, kUmPerPx), "type");
    expectInvalid(pipeline::stitchTiles({{a, {NAN, 0, 0}}}, kUmPerPx), "position");
    expectInvalid(pipeline::stitchTiles({{a, {0, 0, 0}}, {a, {1e9, 0, 0}}}, kUmPerPx), "too large");
}

} // namespace
} // namespace slicestation::test
