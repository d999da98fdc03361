#include "slicestation/pipeline/preprocess.hpp"

#include <gtest/gtest.h>
#include <opencv2/imgproc.hpp>

using namespace slicestation::pipeline;
using slicestation::core::ErrorCode;

namespace {
cv::Mat tissueOnGlass(bool brightGlass, int depth, int channels) {
    cv::Mat img(600, 800, CV_32F, cv::Scalar(brightGlass ? 0.9 : 0.05));
    cv::ellipse(img, {400, 300}, {250, 170}, 0, 0, 360, cv::Scalar(brightGlass ? 0.4 : 0.6),
                cv::FILLED);
    cv::Mat n(img.size(), CV_32F);
    cv::RNG(9).fill(n, cv::RNG::NORMAL, 0, 0.02);
    img += n;
    const double full = depth == CV_8U ? 255.0 : depth == CV_16U ? 65535.0 : 1.0;
    cv::Mat out;
    img.convertTo(out, depth, full);
    if (channels == 3)
        cv::cvtColor(out, out, cv::COLOR_GRAY2BGR);
    if (channels == 2)
        cv::merge(std::vector<cv::Mat>{out, cv::Mat::zeros(out.size(), out.type())}, out);
    return out;
}
} // namespace

TEST(PrepareSection, FluorescenceAndBrightfieldGiveTheSameTissue) {
    for (int depth : {CV_8U, CV_16U, CV_32F}) {
        for (int ch : {1, 2, 3}) {
            auto f = prepareSection(tissueOnGlass(false, depth, ch), 400);
            auto b = prepareSection(tissueOnGlass(true, depth, ch), 400);
            ASSERT_TRUE(f.ok()) << f.error().message;
            ASSERT_TRUE(b.ok()) << b.error().message;
            EXPECT_EQ(f->contrast, Contrast::Fluorescence);
            EXPECT_EQ(b->contrast, Contrast::Brightfield);
            EXPECT_DOUBLE_EQ(f->scale, 0.5);
            EXPECT_EQ(f->grey.size(), cv::Size(400, 300));
            // Ellipse area pi*125*85 at working scale.
            const double expected = CV_PI * 125 * 85;
            EXPECT_NEAR(cv::countNonZero(f->tissueMask), expected, 0.05 * expected);
            EXPECT_NEAR(cv::countNonZero(b->tissueMask), expected, 0.05 * expected);
            // Tissue is bright in the working image whatever the stain.
            EXPECT_GT(b->grey.at<float>(150, 200), b->grey.at<float>(5, 5));
        }
    }
}

TEST(PrepareSection, RejectsBlankEmptyAndTinyImages) {
    EXPECT_EQ(prepareSection(cv::Mat(), 512).error().code, ErrorCode::InvalidArgument);
    EXPECT_EQ(prepareSection(cv::Mat(20, 20, CV_8U, cv::Scalar(3)), 512).error().code,
              ErrorCode::InvalidArgument);
    EXPECT_EQ(prepareSection(cv::Mat(300, 300, CV_8U, cv::Scalar(3)), 512).error().code,
              ErrorCode::NoTissue);
    cv::Mat noise(300, 300, CV_8U);
    cv::RNG(1).fill(noise, cv::RNG::UNIFORM, 0, 20);
    EXPECT_EQ(prepareSection(noise, 512).error().code, ErrorCode::NoTissue);
    EXPECT_EQ(prepareSection(cv::Mat(300, 300, CV_64F, cv::Scalar(1)), 512).error().code,
              ErrorCode::InvalidArgument);
}

// A detached piece of tissue is kept however small down to kMinFragmentShare of the section when
// it is solid and whole in the frame; thin debris (a fibre, a bubble's ring) of the same area,
// and a piece cut by the image's edge (a neighbouring section reaching in), are not.
TEST(PrepareSection, KeepsASmallSolidFragmentAndDropsThinDebrisAndFrameCutPieces) {
    cv::Mat img(600, 800, CV_32F, cv::Scalar(0.05));
    const cv::Scalar tissue(0.6);
    cv::ellipse(img, {400, 300}, {250, 170}, 0, 0, 360, tissue, cv::FILLED); // area ~133500
    cv::circle(img, {90, 520}, 16, tissue, cv::FILLED);             // fragment: ~800 px, 0.6%, r 16
    cv::circle(img, {720, 80}, 45, tissue, 3);                      // ring: ~850 px, 1.5 px thin
    cv::line(img, {40, 40}, {300, 110}, tissue, 4);                 // fibre: ~1100 px, 2 px thin
    cv::rectangle(img, {770, 420}, {799, 450}, tissue, cv::FILLED); // cut by the right edge
    cv::Mat n(img.size(), CV_32F);
    cv::RNG(5).fill(n, cv::RNG::NORMAL, 0, 0.02);
    img += n;
    auto p = prepareSection(img, 800);
    ASSERT_TRUE(p.ok()) << p.error().message;
    ASSERT_EQ(p->scale, 1.0);
    const cv::Mat& m = p->tissueMask;
    EXPECT_EQ(m.at<std::uint8_t>(520, 90), 255) << "the fragment is tissue";
    EXPECT_EQ(m.at<std::uint8_t>(35, 720), 0) << "the ring is debris";
    EXPECT_EQ(m.at<std::uint8_t>(75, 170), 0) << "the fibre is debris";
    EXPECT_EQ(m.at<std::uint8_t>(435, 790), 0) << "a piece cut by the frame is not judged";
    EXPECT_EQ(m.at<std::uint8_t>(300, 400), 255);
}

// A band of doubled tissue (a fold) thin enough to lie above the image's 99.5% level: the grey
// clips it, the level keeps it twice as far above the glass as the tissue beside it, in
// fluorescence (twice the light) and in brightfield (twice the light taken away).
TEST(PrepareSection, TheLevelKeepsTheBrightestTissueTheGreyClips) {
    for (const bool brightGlass : {false, true}) {
        const float glass = brightGlass ? 0.9f : 0.05f, step = brightGlass ? -0.3f : 0.3f;
        cv::Mat img(600, 800, CV_32F, cv::Scalar(glass));
        cv::ellipse(img, {400, 300}, {250, 170}, 0, 0, 360, cv::Scalar(glass + step), cv::FILLED);
        cv::rectangle(img, cv::Rect(300, 200, 60, 12), cv::Scalar(glass + 2 * step), cv::FILLED);
        cv::Mat n(img.size(), CV_32F);
        cv::RNG(5).fill(n, cv::RNG::NORMAL, 0, 0.01);
        img += n;
        cv::Mat img16;
        img.convertTo(img16, CV_16U, 65535);
        auto p = prepareSection(img16, 800);
        ASSERT_TRUE(p.ok()) << p.error().message;
        ASSERT_EQ(p->level.size(), p->grey.size());
        ASSERT_EQ(p->level.type(), CV_32F);
        const cv::Rect band(305, 202, 50, 8), beside(305, 240, 50, 8), outside(20, 20, 50, 50);
        const auto at = [](const cv::Mat& m, const cv::Rect& r) { return cv::mean(m(r))[0]; };
        const double levelRatio = (at(p->level, band) - at(p->level, outside)) /
                                  (at(p->level, beside) - at(p->level, outside));
        const double greyRatio = (at(p->grey, band) - at(p->grey, outside)) /
                                 (at(p->grey, beside) - at(p->grey, outside));
        EXPECT_NEAR(levelRatio, 2.0, 0.1) << (brightGlass ? "brightfield" : "fluorescence");
        EXPECT_LT(greyRatio, 1.3) << (brightGlass ? "brightfield" : "fluorescence");
        // Below the clip level the two agree.
        EXPECT_NEAR(at(p->level, beside), at(p->grey, beside), 1e-3);
    }
}
