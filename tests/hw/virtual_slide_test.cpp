// Virtual slides (generated and loaded) and the simulated camera looking at them.
#include "slicestation/sim/faulty_camera.hpp"
#include "slicestation/sim/sim_camera.hpp"
#include "slicestation/sim/virtual_slide.hpp"

#include <gtest/gtest.h>

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <filesystem>
#include <iostream>

namespace slicestation::test {
namespace {

using namespace std::chrono_literals;
using core::ErrorCode;

sim::VirtualSlideSpec smallSpec() {
    sim::VirtualSlideSpec s;
    s.sections = {{0.3, "", 1}, {0.5, "tear", 2}, {0.7, "missing", 3}};
    s.columns = 2;
    s.sectionPitchUm = 3'000;
    s.sectionWidthUm = 2'600;
    s.umPerPx = 8;
    s.originXUm = 7'000;
    s.originYUm = 4'000;
    s.marginUm = 500;
    return s;
}

const sim::VirtualSlide& smallSlide() {
    static const sim::VirtualSlide v = sim::makeVirtualSlide(smallSpec()).value();
    return v;
}

double meanAround(const cv::Mat& img, cv::Point2d px, int r) {
    cv::Mat g;
    img(cv::Rect(static_cast<int>(px.x) - r, static_cast<int>(px.y) - r, 2 * r, 2 * r))
        .convertTo(g, CV_64F);
    return cv::mean(g)[0];
}

TEST(VirtualSlide, GeneratedSectionsSitWhereTheSlideSays) {
    const auto& v = smallSlide();
    ASSERT_EQ(v.sections.size(), 3u);
    EXPECT_EQ(v.image.type(), CV_16UC1);
    EXPECT_DOUBLE_EQ(v.umPerPx, 8);
    // 2 columns x 2 rows of 3 mm cells plus 0.5 mm margins: 7 mm = 875 px each way.
    EXPECT_EQ(v.image.cols, 875);
    EXPECT_EQ(v.image.rows, 875);
    EXPECT_DOUBLE_EQ(v.sections[0].centre.xUm, 7'000 + 500 + 1'500);
    EXPECT_DOUBLE_EQ(v.sections[1].centre.xUm, 7'000 + 500 + 4'500);
    EXPECT_DOUBLE_EQ(v.sections[2].centre.yUm, 4'000 + 500 + 4'500);
    EXPECT_EQ(v.sections[1].damage, "tear");
    EXPECT_DOUBLE_EQ(v.sections[2].apFraction, 0.7);
    EXPECT_NEAR(v.sections[0].widthUm, 2'600, 8);
    for (const auto& s : v.sections) { // tissue at each centre, glass between the cells
        const cv::Point2d c((s.centre.xUm - v.originXUm) / v.umPerPx,
                            (s.centre.yUm - v.originYUm) / v.umPerPx);
        EXPECT_GT(meanAround(v.image, c, 20), meanAround(v.image, {c.x, c.y - 180}, 5) + 2000)
            << s.index;
    }
    // The empty fourth cell is plain glass.
    EXPECT_LT(meanAround(v.image, {(500 + 4'500) / 8.0, (500 + 4'500) / 8.0}, 50),
              meanAround(v.image, {(500 + 1'500) / 8.0, (500 + 1'500) / 8.0}, 20) / 3);
}

TEST(VirtualSlide, DeterministicAndDamageChangesTheSection) {
    auto a = sim::makeVirtualSlide(smallSpec()).value();
    EXPECT_EQ(cv::norm(a.image, smallSlide().image, cv::NORM_INF), 0);
    auto spec = smallSpec();
    spec.sections[1].damage = "";
    auto b = sim::makeVirtualSlide(spec).value();
    EXPECT_GT(cv::norm(a.image, b.image, cv::NORM_L1), 0);
}

TEST(VirtualSlide, Brightfield) {
    auto spec = smallSpec();
    spec.brightfield = true;
    spec.sections.resize(1);
    auto v = sim::makeVirtualSlide(spec).value();
    ASSERT_EQ(v.image.type(), CV_8UC3);
    const cv::Point2d c((v.sections[0].centre.xUm - v.originXUm) / 8,
                        (v.sections[0].centre.yUm - v.originYUm) / 8);
    cv::Mat g;
    cv::cvtColor(v.image, g, cv::COLOR_BGR2GRAY);
    EXPECT_LT(meanAround(g, c, 20) + 20, meanAround(g, {5, 5}, 4)) << "tissue darker than glass";
}

TEST(VirtualSlide, BadSpecsNameTheField) {
    struct Case {
        std::function<void(sim::VirtualSlideSpec&)> change;
        std::string field;
    };
    const std::vector<Case> cases{
        {[](auto& s) { s.sections.clear(); }, "sections"},
        {[](auto& s) { s.columns = 0; }, "columns"},
        {[](auto& s) { s.umPerPx = 0; }, "umPerPx"},
        {[](auto& s) { s.sectionPitchUm = -1; }, "sectionPitchUm"},
        {[](auto& s) { s.sectionWidthUm = 5'000; }, "sectionWidthUm"},
        {[](auto& s) { s.sectionWidthUm = 10; }, "sectionWidthUm"},
        {[](auto& s) { s.sections[1].damage = "burnt"; }, "sections[1].damage"},
        {[](auto& s) { s.sections[2].apFraction = 1.5; }, "sections[2].apFraction"},
        {[](auto& s) { s.marginUm = -1; }, "marginUm"},
    };
    for (const auto& c : cases) {
        auto spec = smallSpec();
        c.change(spec);
        auto r = sim::makeVirtualSlide(spec);
        ASSERT_FALSE(r) << c.field;
        EXPECT_EQ(r.error().code, ErrorCode::InvalidArgument);
        EXPECT_NE(r.error().message.find(c.field), std::string::npos) << r.error().message;
    }
}

std::filesystem::path sectionFile(int i) {
    char name[32];
    std::snprintf(name, sizeof name, "Section-%02d.tif", i);
    return std::filesystem::path(SLST_SHARED_DIR) / "sections" / "abba-mouse-series" / name;
}

TEST(VirtualSlide, LoadsRealSectionsOnAGrid) {
    if (!std::filesystem::exists(sectionFile(1)))
        GTEST_SKIP() << "no ../shared/sections";
    auto v =
        sim::loadVirtualSlide({sectionFile(5), sectionFile(10), sectionFile(15)}, 20.0, 2, 14'000);
    ASSERT_TRUE(v) << v.error().message;
    EXPECT_EQ(v->image.type(), CV_16UC1); // two-channel uint16: channel 0 kept
    EXPECT_EQ(v->image.cols, 1400);
    EXPECT_EQ(v->image.rows, 1400);
    ASSERT_EQ(v->sections.size(), 3u);
    EXPECT_DOUBLE_EQ(v->sections[2].centre.xUm, 7'000);
    EXPECT_DOUBLE_EQ(v->sections[2].centre.yUm, 21'000);
    EXPECT_DOUBLE_EQ(v->sections[0].widthUm, 655 * 20.0);
    EXPECT_LT(v->sections[0].apFraction, 0);
    const cv::Point2d c(350, 350);
    EXPECT_GT(meanAround(v->image, c, 30), meanAround(v->image, {700, 700}, 10))
        << "tissue over the gap";
}

TEST(VirtualSlide, LoadErrors) {
    auto r = sim::loadVirtualSlide({"/nonexistent/section.tif"}, 20, 2, 14'000);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::NotFound);
    EXPECT_NE(r.error().message.find("/nonexistent/section.tif"), std::string::npos);
    EXPECT_EQ(sim::loadVirtualSlide({}, 20, 2, 14'000).error().code, ErrorCode::InvalidArgument);
    EXPECT_EQ(sim::loadVirtualSlide({"x.tif"}, 0, 2, 14'000).error().code,
              ErrorCode::InvalidArgument);
    EXPECT_EQ(sim::loadVirtualSlide({"x.tif"}, 20, 0, 14'000).error().code,
              ErrorCode::InvalidArgument);
    if (!std::filesystem::exists(sectionFile(1)))
        GTEST_SKIP() << "no ../shared/sections";
    r = sim::loadVirtualSlide({sectionFile(1)}, 20, 2, 5'000); // 13 mm image in a 5 mm cell
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::InvalidArgument);
}

struct Camera {
    hw::StagePosition stage{};
    std::unique_ptr<sim::SimCamera> camera;
};

std::unique_ptr<Camera> cameraOn(const sim::VirtualSlide& v, double sensorUmPerPx) {
    auto c = std::make_unique<Camera>();
    sim::SimCameraConfig cc;
    cc.sensorUmPerPx = sensorUmPerPx;
    cc.focusZUm = 0;
    cc.focusTiltX = cc.focusTiltY = 0;
    auto* st = &c->stage;
    cc.stagePosition = [st] { return *st; };
    c->camera = sim::SimCamera::create(v, cc).value();
    return c;
}

cv::Mat toMat(const hw::Frame& f) {
    return cv::Mat(f.height(), f.width(),
                   f.format() == hw::PixelFormat::Mono16 ? CV_16UC1 : CV_8UC1,
                   const_cast<std::uint8_t*>(f.bytes().data()))
        .clone();
}

TEST(SimCameraOnVirtualSlide, TheFieldIsTheSlideUnderTheStage) {
    const auto& v = smallSlide();
    auto c = cameraOn(v, 8.0); // sensor pixel = slide pixel: the frame is the slide crop
    hw::CameraSettings s;
    s.format = hw::PixelFormat::Mono16;
    s.width = 200;
    s.height = 150;
    ASSERT_TRUE(c->camera->configure(s, 1s));
    c->stage = v.sections[1].centre;
    auto f = c->camera->capture(1s).value();
    const cv::Mat got = toMat(f);
    const int x0 = static_cast<int>((v.sections[1].centre.xUm - v.originXUm) / 8) - 100;
    const int y0 = static_cast<int>((v.sections[1].centre.yUm - v.originYUm) / 8) - 75;
    cv::Mat want = v.image(cv::Rect(x0, y0, 200, 150));
    cv::Mat diff;
    cv::absdiff(got, want, diff);
    EXPECT_LT(cv::mean(diff)[0], 0.02 * 65535) << "only camera noise differs";
    ASSERT_TRUE(f.metadata.stage);
    EXPECT_DOUBLE_EQ(f.metadata.stage->xUm, v.sections[1].centre.xUm);
}

TEST(SimCameraOnVirtualSlide, FinerSensorCoarserSensorAndOffTheSlide) {
    const auto& v = smallSlide();
    hw::CameraSettings s;
    s.width = 320;
    s.height = 240;
    for (double umPerPx : {1.0, 8.0, 30.0}) {
        auto c = cameraOn(v, umPerPx);
        ASSERT_TRUE(c->camera->configure(s, 1s));
        c->stage = v.sections[0].centre;
        const double tissue = cv::mean(toMat(c->camera->capture(1s).value()))[0];
        c->stage = {v.originXUm - 50'000, v.originYUm - 50'000, 0}; // far off the slide: glass
        const double glass = cv::mean(toMat(c->camera->capture(1s).value()))[0];
        EXPECT_GT(tissue, glass + 5) << umPerPx;
    }
}

TEST(SimCameraOnVirtualSlide, LargeDefocusIsBlurred) {
    const auto& v = smallSlide();
    auto c = cameraOn(v, 2.0);
    hw::CameraSettings s;
    s.width = 1024;
    s.height = 768;
    ASSERT_TRUE(c->camera->configure(s, 1s));
    c->stage = v.sections[0].centre;
    auto sharp = toMat(c->camera->capture(1s).value());
    c->stage.zUm = 2'000; // sigma 300 px: rendered on a coarse grid
    const auto t0 = std::chrono::steady_clock::now();
    auto blurred = toMat(c->camera->capture(1s).value());
    std::cout
        << "1024x768 capture at 300 px defocus: "
        << std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count()
        << " ms (information, not a limit)\n";
    cv::Mat l1, l2; // smoothed first: the camera noise is added after the defocus
    cv::GaussianBlur(sharp, sharp, {}, 3);
    cv::GaussianBlur(blurred, blurred, {}, 3);
    cv::Laplacian(sharp, l1, CV_64F);
    cv::Laplacian(blurred, l2, CV_64F);
    cv::Scalar m1, s1, m2, s2;
    cv::meanStdDev(l1, m1, s1);
    cv::meanStdDev(l2, m2, s2);
    EXPECT_GT(s1[0], 2 * s2[0]);
    EXPECT_NEAR(cv::mean(blurred)[0], cv::mean(sharp)[0], 0.35 * cv::mean(sharp)[0])
        << "blur keeps brightness";
}

TEST(SimCameraOnVirtualSlide, FaultyCameraDisconnectsAfterNFrames) {
    const auto& v = smallSlide();
    auto c = cameraOn(v, 8.0);
    auto f = sim::FaultyCamera::create(std::move(c->camera), std::make_shared<core::VirtualClock>())
                 .value();
    f->disconnectAfter(2);
    EXPECT_TRUE(f->capture(1s));
    EXPECT_TRUE(f->capture(1s));
    EXPECT_EQ(f->capture(1s).error().code, ErrorCode::Disconnected);
    EXPECT_EQ(f->configure(hw::CameraSettings{}, 1s).error().code, ErrorCode::Disconnected);
}

} // namespace
} // namespace slicestation::test
