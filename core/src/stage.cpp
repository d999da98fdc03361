#include "slicestation/core/stage.hpp"

#include <cmath>
#include <sstream>

namespace slicestation::hw {

namespace {
core::Result<void> checkAxis(const char* name, const AxisRange& r, double um) {
    if (std::isfinite(um) && r.contains(um))
        return {};
    std::ostringstream os;
    os << "target " << name << " = " << um << " um is outside the soft limits [" << r.minUm << ", "
       << r.maxUm << "] um";
    return core::makeError(core::ErrorCode::OutOfRange, os.str());
}
} // namespace

core::Result<void> checkWithinLimits(const StageLimits& limits, const StagePosition& target) {
    if (auto r = checkAxis("x", limits.x, target.xUm); !r)
        return r;
    if (auto r = checkAxis("y", limits.y, target.yUm); !r)
        return r;
    if (limits.z)
        if (auto r = checkAxis("z", *limits.z, target.zUm); !r)
            return r;
    return {};
}

} // namespace slicestation::hw
