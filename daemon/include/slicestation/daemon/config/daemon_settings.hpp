#pragma once
/// The daemon's part of the station file: `[daemon]` (state, atlas, HTTP) and `[scan]` (what a
/// run uses: objective and its calibrated pixel size, camera-to-stage mapping, exposure, focus,
/// tiling, retries, disk threshold) and `[damage]` (flag_score: the damage score from which a
/// section is flagged, docs/damage.md). `[scan]` and `[damage]` are snapshotted into every run when
/// it is submitted and a run (also a resumed one) always uses its own snapshot.
///
/// ```toml
/// [daemon]
/// state_dir = "/var/lib/slicestation"   # --state-dir and $STATE_DIRECTORY take precedence
/// atlas = "builtin"                     # or a stack directory (slicectl atlas slice)
/// http_bind = "127.0.0.1"
/// http_port = 8470
/// token = "..."                         # or token_file = "/etc/slicestation/token"
/// watchdog_stall_s = 120
/// [scan]
/// objective = "4x"
/// exposure_us = 20000
/// gain = 1.0
/// [scan.objectives.4x]
/// um_per_px = 8.0
/// camera_to_stage = [1.0, 0.0, 0.0, 1.0]  # stage µm per camera px direction, row-major 2x2
/// [damage]
/// flag_score = 0.5   # flagged when the section's damage score reaches it; the threshold set
///                    # through the API (slicectl damage threshold set) takes precedence
/// ```
/// Errors: InvalidArgument naming the key. Strict: a key not read here is refused with the
/// nearest known one (`scan: unknown key "exposur_us"; did you mean "exposure_us"?`), also at
/// the top (kStationTables). `register = false` is refused (registration cannot be skipped yet).
#include "slicestation/core/camera.hpp"
#include "slicestation/core/result.hpp"

#include <nlohmann/json.hpp>

#include <array>
#include <chrono>
#include <cstdint>
#include <filesystem>
#include <string>
#include <string_view>

namespace slicestation::daemon {

/// The tables a station file may have: [stage] and [camera] (station_config), [daemon] and
/// [scan] and [damage] (here), [alerts] (alert_channels).
inline constexpr std::array<std::string_view, 6> kStationTables = {"stage", "camera", "daemon",
                                                                   "scan",  "alerts", "damage"};
inline constexpr std::size_t kMaxTokenBytes = 4096; ///< daemon.token / token_file's first line

struct ObjectiveSettings {
    std::string name = "default";
    double umPerPx = 0; ///< calibrated pixel size at the sample
    /// Unit directions of the camera's x and y axes in the stage frame (row-major 2x2):
    /// stage offset = umPerPx * M * pixel offset. Identity for an aligned camera.
    std::array<double, 4> cameraToStage{1, 0, 0, 1};
};

struct ScanSettings {
    ObjectiveSettings objective;
    hw::CameraSettings camera;
    bool autofocus = true;
    double focusRangeUm = 150;
    double focusCoarseStepUm = 25;
    double focusFineStepUm = 5;
    double minTissueFraction = 0.03;
    double startZUm = 2'500; ///< focus start before the slide's focus surface has points
    double tileOverlap = 0.1;
    int moveRetries = 2;
    int captureRetries = 2;
    std::chrono::milliseconds moveTimeout{10'000};
    std::chrono::milliseconds captureTimeout{5'000};
    std::uint64_t minFreeBytes = 500ull << 20;
    bool checkAtlasMatch = true;
    int mismatchToleranceSlices = 2;
    /// `tilted_planes`: once the run's series model has found the brain's cutting angle from
    /// tilted planes (docs/atlas.md, "Tilted planes in the daemon"), later sections are
    /// registered to planes cut at that angle from the stack's volume instead of its straight
    /// slices. Needs a stack cut from a volume the daemon can read; otherwise straight slices.
    /// A snapshot without the key (older runs) reads false.
    bool tiltedPlanes = true;
    /// The lab's mounting rule: sections lie at most this far turned on the slide (degrees; 180
    /// = any way). Registration does not consider placements turned further.
    double maxTurnDeg = 180;
    /// [damage] flag_score: a section whose damage score (in [0, 1]) reaches this is flagged
    /// damaged. Snapshotted as "damage_flag_score"; a snapshot without it (older runs) reads 0.5.
    double damageFlagScore = 0.5;
    /// Cells per region after each registration (docs/cells.md): `count_cells`, the channel
    /// (`cells_channel`, file order, -1 = grey), `cell_diameter_um` and the Allen structure tree
    /// to roll counts up (`cells_ontology`, a path; empty = the stack's ids without hierarchy).
    bool countCells = false;
    int cellsChannel = -1;
    double cellDiameterUm = 15;
    std::string cellsOntology;
};

struct DaemonSettings {
    std::filesystem::path stateDir;
    std::string atlas = "builtin"; ///< "builtin" or a stack directory
    double builtinIntervalUm = 100;
    std::string httpBind = "127.0.0.1";
    int httpPort =
        8470; ///< 0: choose a free port (tests); the port is written to state_dir/http.port
    std::string token; ///< bearer token for control requests; empty: control refused
    std::chrono::seconds watchdogStall{120};
    ScanSettings scan;
};

/// Reads `[daemon]` and `[scan]` from the station document (readDocument of the station file).
[[nodiscard]] core::Result<DaemonSettings> parseDaemonSettings(const nlohmann::json& station,
                                                               const std::string& origin);
nlohmann::json toJson(const ScanSettings& s);
/// Restores a run's snapshot. InvalidArgument naming the key when the snapshot is damaged.
[[nodiscard]] core::Result<ScanSettings> scanSettingsFromJson(const nlohmann::json& j,
                                                              const std::string& origin);

} // namespace slicestation::daemon
