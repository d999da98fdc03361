#pragma once
// The Camera conformance suite: every model of hw::Camera is instantiated with a factory.
#include "slicestation/core/camera.hpp"

#include <functional>
#include <memory>
#include <string>
#include <vector>

namespace slicestation::test {

struct CameraUnderTest {
    std::shared_ptr<void> rig;          ///< what the camera borrows (stage, device); outlives it
    std::unique_ptr<hw::Camera> camera; ///< destroyed first (declared last)
};

struct CameraModel {
    std::string name;
    std::function<CameraUnderTest()> make;
};

std::vector<CameraModel> cameraModels(); // defined per test executable

} // namespace slicestation::test
