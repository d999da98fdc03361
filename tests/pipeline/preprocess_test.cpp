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
