// The dense refinement's measure and steps on toy images with a known answer.
#include "slicestation/pipeline/dense_refine.hpp"
#include "slicestation/pipeline/registration.hpp"

#include <gtest/gtest.h>
#include <opencv2/imgproc.hpp>

#include <cmath>

using namespace slicestation::pipeline;

namespace {

/// Identity map of a `size` grid: every grid pixel sits on the same atlas pixel.
void identityMap(cv::Size size, cv::Mat& mx, cv::Mat& my) {
    mx.create(size, CV_32F);
    my.create(size, CV_32F);
    for (int y = 0; y < size.height; ++y)
        for (int x = 0; x < size.width; ++x) {
            mx.at<float>(y, x) = float(x);
            my.at<float>(y, x) = float(y);
        }
}

/// Atlas: a square region (id 5) inside a larger region (id 1), glass (0) round it.
cv::Mat squareAtlas(cv::Size size, cv::Rect square) {
    cv::Mat labels = cv::Mat::zeros(size, CV_32S);
    labels(cv::Rect(8, 8, size.width - 16, size.height - 16)).setTo(1);
    labels(square).setTo(5);
    return labels;
}

} // namespace

TEST(DenseRefine, AShiftedSquareFindsItsShift) {
    const cv::Size size(96, 96);
    const cv::Rect square(30, 30, 30, 30);
    const cv::Mat labels = squareAtlas(size, square);
    // The section shows the square 3 px right and 2 px up: the pixel at (33, 28) is the atlas
    // square's corner (30, 30), so the map needs (-3, +2) there.
    cv::Mat grey(size, CV_32F, cv::Scalar(0.05));
    grey(cv::Rect(8, 8, 80, 80)).setTo(0.3);
    grey(square + cv::Point(3, -2)).setTo(0.8);
    cv::Mat noise(size, CV_32F);
    cv::RNG(7).fill(noise, cv::RNG::NORMAL, 0, 0.02);
    grey += noise;
    cv::Mat mx, my;
    identityMap(size, mx, my);
    const cv::Mat weight(size, CV_8U, cv::Scalar(255));
    // The measure's gradient alone, at a scale that suits the toy: no bias term (the square is
    // as large as the smoothing scale of the default), enough steps to cover 3 px.
    DenseRefineOptions toy;
    toy.levels = {{2.0, 4, 30}};
    toy.biasSigma = 0;
    toy.maxStepGridPx = 0.5;
    toy.holdOutBlockPx = 4;
    toy.regionGradients = false;
    const DenseRefinement r = refineDense(grey, weight, mx, my, labels, cv::Mat(), toy);
    ASSERT_TRUE(r.accepted);
    EXPECT_GT(r.explainedAfter, r.explainedBefore + 0.05);
    EXPECT_GT(r.minJacobian, 0.0);
    EXPECT_EQ(r.regions, 2); // 1 and 5 (glass is not counted)
    // Each edge tells the shift across it (the aperture problem leaves the other component to
    // the regularisation): the vertical edges of the shown square move by -3 in x, the
    // horizontal ones by +2 in y.
    for (const cv::Point q : {cv::Point(33, 43), cv::Point(62, 43)})
        EXPECT_NEAR(r.ux.at<float>(q), -3.0, 0.5) << q;
    for (const cv::Point q : {cv::Point(48, 28), cv::Point(48, 57)})
        EXPECT_NEAR(r.uy.at<float>(q), 2.0, 0.5) << q;
    // Without the refinement's steps the map stays where it was (the test fails when broken).
    DenseRefineOptions none = toy;
    for (auto& l : none.levels)
        l.iterations = 0;
    const DenseRefinement idle = refineDense(grey, weight, mx, my, labels, cv::Mat(), none);
    EXPECT_FALSE(idle.accepted);
    EXPECT_EQ(cv::countNonZero(idle.ux), 0);
}

TEST(DenseRefine, AnAtlasIntensityPlaneIsASecondTerm) {
    // The section's contrast inside region 1 follows the atlas intensity (a ramp that the labels
    // cannot show); only with the intensity plane does the refinement find the shift across it.
    const cv::Size size(96, 96);
    cv::Mat labels = cv::Mat::zeros(size, CV_32S);
    labels(cv::Rect(4, 4, 88, 88)).setTo(1);
    cv::Mat intensity(size, CV_32F, cv::Scalar(0));
    cv::Mat grey(size, CV_32F, cv::Scalar(0));
    for (int y = 4; y < 92; ++y)
        for (int x = 4; x < 92; ++x) {
            // A blob in the intensity plane, shown shifted by (+2, +2) in the section.
            auto blob = [](double dx, double dy) { return std::exp(-(dx * dx + dy * dy) / 200.0); };
            intensity.at<float>(y, x) = float(blob(x - 48, y - 48));
            grey.at<float>(y, x) = float(0.2 + 0.5 * blob(x - 50, y - 50));
        }
    cv::Mat mx, my;
    identityMap(size, mx, my);
    cv::Mat weight = cv::Mat::zeros(size, CV_8U);
    weight(cv::Rect(4, 4, 88, 88)).setTo(255);
    const DenseRefinement labelsOnly = refineDense(grey, weight, mx, my, labels, cv::Mat());
    const DenseRefinement both = refineDense(grey, weight, mx, my, labels, intensity);
    ASSERT_TRUE(both.accepted);
    const cv::Point c(50, 50);
    EXPECT_NEAR(both.ux.at<float>(c), -2.0, 0.6);
    EXPECT_NEAR(both.uy.at<float>(c), -2.0, 0.6);
    EXPECT_LT(std::abs(labelsOnly.ux.at<float>(c)), 0.5);
}

TEST(DenseRefine, ConfidenceIsLowWhereTheSectionContradictsTheAtlas) {
    const cv::Size size(128, 96);
    const cv::Rect square(40, 30, 30, 30);
    const cv::Mat labels = squareAtlas(size, square);
    cv::Mat grey(size, CV_32F, cv::Scalar(0.05));
    grey(cv::Rect(8, 8, size.width - 16, size.height - 16)).setTo(0.3);
    grey(square).setTo(0.8);
    // A misfit: a patch in region 1 stained like nothing the atlas has there.
    cv::circle(grey, cv::Point(100, 48), 7, cv::Scalar(1.0), cv::FILLED);
    cv::Mat mx, my;
    identityMap(size, mx, my);
    const cv::Mat weight(size, CV_8U, cv::Scalar(255));
    const DenseRefinement r = refineDense(grey, weight, mx, my, labels, cv::Mat());
    const float atMisfit = r.confidence.at<float>(48, 100);
    const float inSquare = r.confidence.at<float>(45, 55);
    const float elsewhere = r.confidence.at<float>(20, 20);
    EXPECT_LT(atMisfit, 0.5f);
    EXPECT_GT(inSquare, 0.8f);
    EXPECT_GT(elsewhere, 0.8f);
    // The map was right: the refinement must not have dragged the square towards the patch.
    EXPECT_LT(std::hypot(r.ux.at<float>(45, 55), r.uy.at<float>(45, 55)), 0.5);
    // Per region: region 5 is trusted more than region 1, which holds the misfit.
    cv::Mat valid(size, CV_8U, cv::Scalar(255));
    const auto byRegion = meanByLabel(r.confidence, labels, valid);
    ASSERT_EQ(byRegion.size(), 2u);
    EXPECT_EQ(byRegion[0].first, 1); // the larger region first
    EXPECT_GT(byRegion[1].second, byRegion[0].second);
}

TEST(DenseRefine, BadRefinementOptionsAreRefusedByRegisterSection) {
    const cv::Mat labels = squareAtlas({96, 96}, cv::Rect(30, 30, 30, 30));
    cv::Mat section(200, 200, CV_8U, cv::Scalar(10));
    cv::rectangle(section, cv::Rect(40, 40, 120, 120), cv::Scalar(200), cv::FILLED);
    RegistrationOptions wrongPlane;
    wrongPlane.atlasIntensity = cv::Mat(50, 50, CV_32F, cv::Scalar(0));
    auto r = registerSection(section, labels, wrongPlane);
    ASSERT_FALSE(r.ok());
    EXPECT_EQ(r.error().code, slicestation::core::ErrorCode::InvalidArgument);
    EXPECT_NE(r.error().message.find("atlas intensity"), std::string::npos);
    RegistrationOptions wrongType;
    wrongType.atlasIntensity = cv::Mat(96, 96, CV_8U, cv::Scalar(0));
    EXPECT_EQ(registerSection(section, labels, wrongType).error().code,
              slicestation::core::ErrorCode::InvalidArgument);
    RegistrationOptions noLevels;
    noLevels.dense.levels.clear();
    r = registerSection(section, labels, noLevels);
    ASSERT_FALSE(r.ok());
    EXPECT_NE(r.error().message.find("dense refinement"), std::string::npos);
    RegistrationOptions tinyGrid;
    tinyGrid.dense.gridMaxSide = 8;
    EXPECT_EQ(registerSection(section, labels, tinyGrid).error().code,
              slicestation::core::ErrorCode::InvalidArgument);
}
