#pragma once
// A simulated stage with a simulated camera looking at a small generated slide (tests only).
#include "slicestation/sim/faulty_camera.hpp"
#include "slicestation/sim/sim_camera.hpp"
#include "slicestation/sim/sim_stage.hpp"

#include <memory>

namespace slicestation::test {

struct SimRig {
    std::unique_ptr<sim::SimStage> stage;
    std::unique_ptr<hw::Camera> camera; ///< SimCamera, or FaultyCamera around it
    sim::SimCamera* simCamera = nullptr;
    std::shared_ptr<core::VirtualClock> clock;
};

/// Slide: 2 generated sections of 600 x 500 px at 2 µm/px; stage limits cover it.
SimRig makeSimRig(bool faulty);

} // namespace slicestation::test
