// The steps of one section and the one retry policy, against the simulated stage and camera with
// injected faults: no scan loop, no HTTP, no registration.
#include "slicestation/daemon/station/retry_policy.hpp"
#include "slicestation/daemon/station/section_steps.hpp"
#include "slicestation/daemon/storage/ome_tiff.hpp"

#include "slicestation/sim/faulty_camera.hpp"
#include "slicestation/sim/faulty_stage.hpp"
#include "slicestation/sim/sim_camera.hpp"
#include "slicestation/sim/sim_stage.hpp"

#include "../../common/test_dir.hpp"

#include <gtest/gtest.h>

#include <filesystem>
#include <memory>

namespace slicestation::test {
namespace {

using namespace std::chrono_literals;
using core::ErrorCode;
using core::makeError;
using daemon::SectionSteps;

constexpr double kFocusZ = 2'500;

struct Rig {
    std::shared_ptr<core::VirtualClock> clock = std::make_shared<core::VirtualClock>();
    std::unique_ptr<hw::Stage> stage;
    std::unique_ptr<hw::Camera> camera;
    sim::FaultyStage* faultyStage = nullptr;
    sim::FaultyCamera* faultyCamera = nullptr;
    daemon::PhaseStats stats;
    daemon::ScanSettings settings;
    std::filesystem::path dir;
    std::uint64_t freeBytes = 1ull << 40;
    std::unique_ptr<daemon::Journal> journal;

    Rig() {
        static const cv::Mat slide = sim::makeGeneratedSlide(2, {600, 500}, 11).value();
        sim::SimStageConfig sc;
        sc.clock = clock; // moves take virtual time: instant here
        auto simStage = sim::SimStage::create(sc).value();
        sim::SimCameraConfig cc;
        cc.slide = slide;
        cc.slideUmPerPx = 2.0;
        cc.sensorUmPerPx = 2.0;
        cc.focusZUm = kFocusZ;
        auto* st = simStage.get();
        cc.stagePosition = [st] { return st->peekPosition(); };
        auto fs = sim::FaultyStage::create(std::move(simStage), clock).value();
        auto fc = sim::FaultyCamera::create(sim::SimCamera::create(cc).value(), clock).value();
        faultyStage = fs.get();
        faultyCamera = fc.get();
        stage = std::move(fs);
        camera = std::move(fc);
        settings.objective.umPerPx = 2.0;
        settings.camera.format = hw::PixelFormat::Mono16;
        settings.camera.width = 320; // a 640 x 480 um field
        settings.camera.height = 240;
        settings.moveRetries = 1;
        settings.captureRetries = 1;
        settings.moveTimeout = 1s;
        settings.captureTimeout = 1s;
        settings.autofocus = false;
        dir = testing_dir::freshTestDir("steps");
        journal = daemon::Journal::open(dir / "journal.sqlite").value();
    }
    ~Rig() { std::filesystem::remove_all(dir); }
    SectionSteps steps() {
        return SectionSteps({*stage, *camera, stats, dir,
                             [this](const std::filesystem::path&) -> core::Result<std::uint64_t> {
                                 return freeBytes;
                             },
                             nullptr},
                            settings);
    }
};

daemon::SectionRecord section(double widthUm, double heightUm) {
    daemon::SectionRecord s;
    s.id = 1;
    s.name = "s1";
    s.slideName = "slide-01";
    s.xUm = 600;
    s.yUm = 500;
    s.widthUm = widthUm;
    s.heightUm = heightUm;
    return s;
}

TEST(RetryPolicy, RetriesAllButCancelledOutOfRangeAndAlarm) {
    for (ErrorCode code : {ErrorCode::Cancelled, ErrorCode::OutOfRange, ErrorCode::Alarm})
        EXPECT_FALSE(daemon::worthRetrying(makeError(code, ""))) << core::toString(code);
    for (ErrorCode code :
         {ErrorCode::Timeout, ErrorCode::Disconnected, ErrorCode::IoError, ErrorCode::Internal})
        EXPECT_TRUE(daemon::worthRetrying(makeError(code, ""))) << core::toString(code);
}

TEST(RetryPolicy, MovesGetOneAttemptPerRetryButNeverAfterAnAlarm) {
    Rig rig;
    rig.faultyStage->failNext(sim::FaultyStage::Op::Move,
                              makeError(ErrorCode::Timeout, "x drive timeout"));
    EXPECT_TRUE(daemon::moveWithRetries(*rig.stage, {100, 100, kFocusZ}, 1s, 1))
        << "the retry settles";
    rig.faultyStage->failNext(sim::FaultyStage::Op::Move,
                              makeError(ErrorCode::Timeout, "x drive timeout"));
    auto none = daemon::moveWithRetries(*rig.stage, {100, 100, kFocusZ}, 1s, 0);
    ASSERT_FALSE(none);
    EXPECT_EQ(none.error().code, ErrorCode::Timeout);
    rig.faultyStage->failNext(sim::FaultyStage::Op::Move,
                              makeError(ErrorCode::Alarm, "z drive alarm 0x42"));
    auto alarm = daemon::moveWithRetries(*rig.stage, {100, 100, kFocusZ}, 1s, 3);
    ASSERT_FALSE(alarm) << "an alarm was retried (the next attempt would have settled)";
    EXPECT_EQ(alarm.error().code, ErrorCode::Alarm);
}

TEST(RetryPolicy, CapturesAreRetriedAfterReinitialisingTheCamera) {
    Rig rig;
    ASSERT_TRUE(rig.camera->configure(rig.settings.camera, 1s));
    rig.faultyCamera->timeoutNext(2);
    EXPECT_TRUE(daemon::captureWithRetries(*rig.camera, 1s, 2, rig.settings.camera))
        << "third attempt";
    rig.faultyCamera->timeoutNext(3);
    auto failed = daemon::captureWithRetries(*rig.camera, 1s, 2, rig.settings.camera);
    ASSERT_FALSE(failed);
    EXPECT_EQ(failed.error().code, ErrorCode::Timeout);
}

TEST(SectionSteps, FieldOfViewFollowsTheCameraAndTheObjective) {
    Rig rig;
    rig.settings.objective.cameraToStage = {0, 1, 1, 0}; // camera axes swapped on the stage
    SectionSteps steps = rig.steps();
    auto used = steps.configureCamera();
    ASSERT_TRUE(used);
    EXPECT_EQ(used->width, 320);
    EXPECT_DOUBLE_EQ(steps.fieldWidthUm(), 480); // 240 px rows along stage x
    EXPECT_DOUBLE_EQ(steps.fieldHeightUm(), 640);
}

TEST(SectionSteps, ALargeSectionIsCapturedAsTilesAndStitched) {
    Rig rig;
    SectionSteps steps = rig.steps();
    ASSERT_TRUE(steps.configureCamera());
    std::string told;
    auto one = steps.capture(section(0, 0), kFocusZ, [&](const std::string& s) { told = s; });
    ASSERT_TRUE(one) << one.fault().error.message;
    EXPECT_EQ(one->tiles, 1);
    EXPECT_EQ(one->image.cols, 320);
    EXPECT_EQ(one->image.rows, 240);
    EXPECT_TRUE(told.empty());
    auto tiled =
        steps.capture(section(1000, 700), kFocusZ, [&](const std::string& s) { told = s; });
    ASSERT_TRUE(tiled) << tiled.fault().error.message;
    EXPECT_EQ(tiled->tiles, 4);        // 2 x 2 fields of 640 x 480 um with 10 % overlap
    EXPECT_GE(tiled->image.cols, 500); // >= 1000 um at 2 um/px
    EXPECT_GE(tiled->image.rows, 350);
    EXPECT_EQ(told, "stitching 4 tiles");
    EXPECT_DOUBLE_EQ(tiled->stage.xUm, 600);
}

TEST(SectionSteps, EachFaultIsNamedByTheDeviceThatFailed) {
    Rig rig;
    SectionSteps steps = rig.steps();
    ASSERT_TRUE(steps.configureCamera());
    rig.faultyCamera->timeoutNext(2); // beyond the one retry
    auto capture = steps.capture(section(0, 0), kFocusZ, {});
    ASSERT_FALSE(capture);
    EXPECT_EQ(capture.fault().kind, daemon::AlertKind::CameraFault);
    EXPECT_EQ(capture.fault().error.code, ErrorCode::Timeout);

    rig.faultyStage->alarmOnNextMove(0x42);
    auto move = steps.move({600, 500, kFocusZ});
    ASSERT_FALSE(move);
    EXPECT_EQ(move.fault().kind, daemon::AlertKind::StageFault);
    EXPECT_EQ(move.fault().error.code, ErrorCode::Alarm);
    ASSERT_TRUE(rig.stage->resetAlarm(1s));

    rig.settings.autofocus = true;
    rig.faultyStage->disconnectAfter(1); // the focus sweep's first move finds the stage gone
    ASSERT_TRUE(steps.move({600, 500, kFocusZ}));
    auto focus = steps.focus(600, 500, kFocusZ);
    ASSERT_FALSE(focus);
    EXPECT_EQ(focus.fault().kind, daemon::AlertKind::StageFault);

    rig.freeBytes = 1 << 20;
    auto disk = steps.checkDisk();
    ASSERT_TRUE(disk);
    EXPECT_EQ(disk->kind, daemon::AlertKind::LowDisk);
}

TEST(SectionSteps, FocusIsSkippedWhenTheRunAsksNone) {
    Rig rig;
    SectionSteps steps = rig.steps();
    auto focus = steps.focus(600, 500, 2'400);
    ASSERT_TRUE(focus);
    EXPECT_FALSE(focus->found);
    EXPECT_DOUBLE_EQ(focus->zUm, 2'400);
}

TEST(SectionSteps, AnImageNoCaptureRefersToIsReplacedOneACaptureRefersToNever) {
    Rig rig;
    SectionSteps steps = rig.steps();
    auto used = steps.configureCamera();
    ASSERT_TRUE(used);
    auto captured = steps.capture(section(0, 0), kFocusZ, {});
    ASSERT_TRUE(captured);
    daemon::RunRecord run;
    run.id = 3;
    const auto rel = daemon::imagePathFor(run, section(0, 0), 1);
    EXPECT_EQ(rel, std::filesystem::path("runs/3/01-slide-01/1-s1-a1.ome.tif"));
    EXPECT_FALSE(steps.writeImage(rel, *captured, "r / slide-01 / s1", *used, *rig.journal));
    EXPECT_TRUE(daemon::readOmeTiff(rig.dir / rel));
    EXPECT_FALSE(steps.writeImage(rel, *captured, "again", *used, *rig.journal))
        << "an orphan is replaced";

    daemon::PlannedSection planned;
    planned.slideName = "slide-01";
    planned.name = "s1";
    auto runId =
        rig.journal->createRun("r", nlohmann::json::object(), nlohmann::json::object(), {planned});
    ASSERT_TRUE(runId);
    auto sec = rig.journal->nextSectionToCapture(*runId);
    ASSERT_TRUE(sec && *sec);
    daemon::CaptureRecord rec;
    rec.sectionId = (*sec)->id;
    rec.imagePath = rel.string();
    rec.umPerPx = 2;
    ASSERT_TRUE(rig.journal->recordCapture(rec));
    auto refused = steps.writeImage(rel, *captured, "third", *used, *rig.journal);
    ASSERT_TRUE(refused);
    EXPECT_EQ(refused->kind, daemon::AlertKind::StorageFault);
    EXPECT_EQ(refused->error.sysErrno, EEXIST);
}

} // namespace
} // namespace slicestation::test
