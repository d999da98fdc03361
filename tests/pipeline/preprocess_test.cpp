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
