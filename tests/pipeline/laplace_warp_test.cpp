#include "slicestation/pipeline/laplace_warp.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>

using namespace slicestation::pipeline;

TEST(LaplaceWarp, ConstantBoundaryGivesConstantField) {
    std::vector<cv::Point2d> pts, disp;
    for (int i = 0; i < 400; ++i) {
        const double t = 2 * CV_PI * i / 400;
        pts.emplace_back(500 + 300 * std::cos(t), 400 + 250 * std::sin(t));
        disp.emplace_back(3.0, -2.0);
    }
    const auto f = solveLaplaceWarp({1000, 800}, pts, disp);
    for (const cv::Point2d p :
         {cv::Point2d(500, 400), cv::Point2d(10, 10), cv::Point2d(990, 790)}) {
        EXPECT_NEAR(f.at(p).x, 3.0, 0.05);
        EXPECT_NEAR(f.at(p).y, -2.0, 0.05);
    }
}

TEST(LaplaceWarp, InterpolatesBetweenTwoCurvesAndHoldsTheConditions) {
    // u = 0 on the line x = 200, u = 10 on x = 800: between them the harmonic solution is linear.
    std::vector<cv::Point2d> pts, disp;
    for (int y = 0; y <= 600; y += 2) {
        pts.emplace_back(200, y);
        disp.emplace_back(0, 0);
        pts.emplace_back(800, y);
        disp.emplace_back(10, 0);
    }
    LaplaceOptions o;
    o.sweepsPerLevel = 80;
    const auto f = solveLaplaceWarp({1000, 600}, pts, disp, o);
    EXPECT_NEAR(f.at({200, 300}).x, 0.0, 1e-4);
    EXPECT_NEAR(f.at({800, 300}).x, 10.0, 1e-4);
    EXPECT_NEAR(f.at({500, 300}).x, 5.0, 0.3);
    EXPECT_NEAR(f.at({350, 100}).x, 2.5, 0.3);
    EXPECT_NEAR(f.at({900, 300}).x, 10.0, 0.3); // Neumann border beyond the last curve
}

TEST(LaplaceWarp, NoPointsGivesAnEmptyZeroField) {
    const auto f = solveLaplaceWarp({100, 100}, {}, {});
    EXPECT_TRUE(f.empty());
    EXPECT_EQ(f.at({5, 5}), cv::Point2d(0, 0));
}

TEST(LaplaceWarp, RelaxWithinUndoesAFoldAndMovesNothingElse) {
    // A smooth (linear) field with one node pushed 20 px along x, five cells of 4 px: the map
    // x + u folds beside it. Relaxing the 5 x 5 nodes around it gives back the linear field
    // there (the harmonic interpolation of a linear field is linear); every other node is held.
    const int rows = 40, cols = 50;
    const double cell = 4;
    cv::Mat dx(rows, cols, CV_32F), dy(rows, cols, CV_32F);
    for (int i = 0; i < rows; ++i)
        for (int j = 0; j < cols; ++j) {
            dx.at<float>(i, j) = float(0.1 * j * cell + 10);
            dy.at<float>(i, j) = float(-0.05 * i * cell);
        }
    const cv::Mat smoothX = dx.clone(), smoothY = dy.clone();
    dx.at<float>(20, 25) += 20;
    const DisplacementField folded(dx, dy, cell);
    const auto minJacobian = [&](const DisplacementField& f) {
        double m = 1e9;
        for (int i = 1; i + 1 < rows; ++i)
            for (int j = 1; j + 1 < cols; ++j) {
                const double xx =
                    1 + (f.dx().at<float>(i, j + 1) - f.dx().at<float>(i, j - 1)) / (2 * cell);
                const double xy =
                    (f.dx().at<float>(i + 1, j) - f.dx().at<float>(i - 1, j)) / (2 * cell);
                const double yx =
                    (f.dy().at<float>(i, j + 1) - f.dy().at<float>(i, j - 1)) / (2 * cell);
                const double yy =
                    1 + (f.dy().at<float>(i + 1, j) - f.dy().at<float>(i - 1, j)) / (2 * cell);
                m = std::min(m, xx * yy - xy * yx);
            }
        return m;
    };
    ASSERT_LT(minJacobian(folded), 0);
    cv::Mat region = cv::Mat::zeros(rows, cols, CV_8U);
    region(cv::Rect(23, 18, 5, 5)).setTo(255);
    const DisplacementField relaxed = relaxWithin(folded, region);
    EXPECT_GT(minJacobian(relaxed), 0.5);
    for (int i = 0; i < rows; ++i)
        for (int j = 0; j < cols; ++j) {
            if (region.at<uchar>(i, j)) {
                EXPECT_NEAR(relaxed.dx().at<float>(i, j), smoothX.at<float>(i, j), 1e-3);
                EXPECT_NEAR(relaxed.dy().at<float>(i, j), smoothY.at<float>(i, j), 1e-3);
            } else {
                EXPECT_EQ(relaxed.dx().at<float>(i, j), folded.dx().at<float>(i, j));
                EXPECT_EQ(relaxed.dy().at<float>(i, j), folded.dy().at<float>(i, j));
            }
        }
    // At the grid's edge the free nodes have mirror borders: a corner block relaxes to the
    // held values around it, not to zero.
    cv::Mat corner = cv::Mat::zeros(rows, cols, CV_8U);
    corner(cv::Rect(0, 0, 3, 3)).setTo(255);
    const DisplacementField c = relaxWithin(DisplacementField(smoothX, smoothY, cell), corner);
    EXPECT_NEAR(c.dx().at<float>(0, 0), smoothX.at<float>(0, 0), 2.0);
}

TEST(LaplaceWarp, TheSweepsGiveWhatPlainRowOrderGivesToTheBit) {
    // One level only (coarsestNodes above the grid), nodes 1 px apart, conditions on nodes:
    // the solver's wavefront sweeps must give the plain row-by-row Gauss-Seidel SOR's values
    // exactly, whatever the grid's row count left over by the wavefront's bands of rows and
    // whether a band's rows are longer or shorter than the band is tall.
    for (const cv::Size domain :
         {cv::Size(97, 70), cv::Size(64, 71), cv::Size(5, 3), cv::Size(40, 18), cv::Size(9, 2),
          cv::Size(12, 11), cv::Size(3, 30)}) {
        cv::RNG rng(static_cast<std::uint64_t>(domain.area()));
        cv::Mat fixed = cv::Mat::zeros(domain, CV_8U);
        cv::Mat fx = cv::Mat::zeros(domain, CV_32F), fy = cv::Mat::zeros(domain, CV_32F);
        std::vector<cv::Point2d> pts, disp;
        for (int k = 0; k < domain.area() / 12 + 1; ++k) {
            const int x = rng.uniform(0, domain.width), y = rng.uniform(0, domain.height);
            if (fixed.at<uchar>(y, x))
                continue;
            fixed.at<uchar>(y, x) = 1;
            const double dx = rng.uniform(-4.0, 4.0), dy = rng.uniform(-4.0, 4.0);
            fx.at<float>(y, x) = float(dx);
            fy.at<float>(y, x) = float(dy);
            pts.emplace_back(x, y);
            disp.emplace_back(dx, dy);
        }
        LaplaceOptions o;
        o.cellPx = 1;
        o.coarsestNodes = 100000;
        o.sweepsCoarsest = 37;
        const auto f = solveLaplaceWarp(domain, pts, disp, o);
        ASSERT_EQ(f.dx().size(), domain);

        const int rows = domain.height, cols = domain.width;
        cv::Mat ux(domain, CV_32F, cv::Scalar(cv::mean(fx, fixed)[0]));
        cv::Mat uy(domain, CV_32F, cv::Scalar(cv::mean(fy, fixed)[0]));
        const float w = float(o.relaxation);
        for (int s = 0; s < o.sweepsCoarsest; ++s)
            for (int i = 0; i < rows; ++i)
                for (int j = 0; j < cols; ++j) {
                    if (fixed.at<uchar>(i, j)) {
                        ux.at<float>(i, j) = fx.at<float>(i, j);
                        uy.at<float>(i, j) = fy.at<float>(i, j);
                        continue;
                    }
                    const int iu = i > 0 ? i - 1 : std::min(1, rows - 1);
                    const int id = i + 1 < rows ? i + 1 : std::max(rows - 2, 0);
                    const int jl = j > 0 ? j - 1 : std::min(1, cols - 1);
                    const int jr = j + 1 < cols ? j + 1 : std::max(cols - 2, 0);
                    for (cv::Mat* u : {&ux, &uy}) {
                        const float avg = 0.25f * (u->at<float>(i, jl) + u->at<float>(i, jr) +
                                                   u->at<float>(iu, j) + u->at<float>(id, j));
                        u->at<float>(i, j) += w * (avg - u->at<float>(i, j));
                    }
                }
        EXPECT_EQ(cv::norm(f.dx(), ux, cv::NORM_INF), 0.0) << domain;
        EXPECT_EQ(cv::norm(f.dy(), uy, cv::NORM_INF), 0.0) << domain;
    }
}
