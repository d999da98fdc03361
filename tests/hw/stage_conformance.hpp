#pragma once
// The Stage conformance suite: every model of hw::Stage is instantiated with a factory.
#include "slicestation/core/stage.hpp"

#include <functional>
#include <memory>
#include <string>

namespace slicestation::test {

struct StageModel {
    std::string name;
    /// slow = false: moves take well under a second of wall time (or are virtual);
    /// slow = true: a long move takes many seconds of wall time (to test stop()).
    std::function<std::unique_ptr<hw::Stage>(bool slow)> make;
};

} // namespace slicestation::test
