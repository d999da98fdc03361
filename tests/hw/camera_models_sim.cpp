// The simulated camera models for the camera conformance suite, and the shared sim rig.
#include "camera_conformance.hpp"
#include "sim_camera_rig.hpp"

#include <cassert>

namespace slicestation::test {

namespace {
const cv::Mat& smallSlide() {
    static const cv::Mat s = sim::makeGeneratedSlide(2, {600, 500}, 7).value();
    return s;
}
} // namespace

SimRig makeSimRig(bool faulty) {
    SimRig r;
    r.clock = std::make_shared<core::VirtualClock>();
    sim::SimStageConfig sc;
    sc.clock = r.clock;
    sc.limits = {{0, 2400}, {0, 1000}, hw::AxisRange{0, 5000}};
    r.stage = sim::SimStage::create(sc).value();
    sim::SimCameraConfig cc;
    cc.slide = smallSlide();
    auto* st = r.stage.get();
    cc.stagePosition = [st] { return st->peekPosition(); };
    cc.focusTiltX = cc.focusTiltY = 0;
    auto cam = sim::SimCamera::create(cc).value();
    r.simCamera = cam.get();
    if (faulty)
        r.camera = sim::FaultyCamera::create(std::move(cam), r.clock).value();
    else
        r.camera = std::move(cam);
    return r;
}

std::vector<CameraModel> cameraModels() {
    auto wrap = [](bool faulty) {
        auto rig = std::make_shared<SimRig>(makeSimRig(faulty));
        CameraUnderTest c;
        c.camera = std::move(rig->camera);
        c.rig = rig; // keeps the stage the camera looks through
        return c;
    };
    return {
        {"SimCamera", [wrap] { return wrap(false); }},
        {"FaultyCameraWithoutFaults", [wrap] { return wrap(true); }},
    };
}

} // namespace slicestation::test
