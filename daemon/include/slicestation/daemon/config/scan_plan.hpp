#pragma once
/// Scan plans: what a technician submits. TOML or JSON of this shape (docs/operation.md):
/// ```toml
/// name = "mouse-42 coronal"
/// [[slides]]
/// name = "slide-01"
/// [[slides.sections]]
/// name = "s01"              # optional, default "s<slide>-<n>"
/// x_um = 11000              # section centre, stage frame
/// y_um = 9000
/// width_um = 10000          # optional; larger than the field of view => tiles
/// height_um = 8000
/// atlas_slice = 12          # index in the atlas stack, or:
/// # atlas_position_um = 4350
/// ```
/// Errors are InvalidArgument naming the file and field (`slides[1].sections[0].y_um: missing`).
/// Every table is strict: a key not shown above is refused (`unknown key "widht_um"; did you
/// mean "width_um"?`).
#include "slicestation/core/result.hpp"
#include "slicestation/core/stage.hpp"
#include "slicestation/daemon/storage/journal.hpp"

#include <nlohmann/json.hpp>

#include <cstddef>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

namespace slicestation::daemon {

/// Slide and section names: 1..kMaxPlanNameBytes bytes, no control characters, no '/' or '\\',
/// not only dots (they name directories and files of the run).
inline constexpr std::size_t kMaxPlanNameBytes = 64;
inline constexpr std::size_t kMaxRunNameBytes = 256; ///< the plan's `name`; no control characters
inline constexpr std::size_t kMaxPlanSections = 10'000; ///< over all slides of one plan
inline constexpr double kMaxPlanCoordinateUm = 1e7;     ///< |x_um|, |y_um|, |atlas_position_um|

struct PlanSection {
    PlannedSection section;
    std::optional<double> atlasPositionUm; ///< when the plan gives a position, not an index
};

struct ScanPlan {
    std::string name;
    std::vector<PlanSection> sections; ///< slide by slide, in plan order
    nlohmann::json document;           ///< the plan as submitted (JSON form)
};

[[nodiscard]] core::Result<ScanPlan> parseScanPlan(const nlohmann::json& document,
                                                   const std::string& origin);

/// Checks the plan against the station: every section's whole extent (centre +- width/2 and
/// height/2) inside the stage's soft limits, every
/// atlas slice inside the stack (`positionsUm[i]` = position of slice i), positions turned into
/// the nearest slice. InvalidArgument naming the section and field.
[[nodiscard]] core::Result<void> resolveScanPlan(ScanPlan& plan, const hw::StageLimits& limits,
                                                 const std::vector<double>& slicePositionsUm,
                                                 const std::string& origin);

} // namespace slicestation::daemon
