#pragma once
/// Cells per region of one registered section (issue 22): detect the cells on a channel
/// (pipeline::detectCells), count them per atlas region with the full ontology
/// (pipeline::countCells), and write COUNTS.csv and CELLS.csv (docs/cells.md). What
/// `slicectl count` and the registration worker call.
///
/// COUNTS.csv: id,acronym,name,parent_id,depth,count,area_mm2,density_per_mm2 (one row per
/// region with tissue or cells and each of its ancestors; damage excluded from counts and areas).
/// CELLS.csv: x,y,ccf_x_um,ccf_y_um,ccf_z_um,id,acronym,atlas_x,atlas_y,excluded,cells (the CCF
/// columns empty unless the atlas is a slice of a stack cut from a volume).
/// Threading: re-entrant. Blocking file I/O in the write functions only.
#include "slicestation/core/ontology.hpp"
#include "slicestation/core/result.hpp"
#include "slicestation/daemon/storage/atlas_stack.hpp"
#include "slicestation/pipeline/cells.hpp"
#include "slicestation/pipeline/registration.hpp"

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include <filesystem>
#include <optional>
#include <string>
#include <vector>

namespace slicestation::daemon {

struct CellCountOptions {
    /// Detector settings; diameterPx is set from cellDiameterUm and imageUmPerPx, the mask from
    /// the registration's tissue.
    pipeline::CellDetectorOptions detector;
    double cellDiameterUm = 15; ///< typical cell body; in [1, 500]
    double imageUmPerPx = 0;    ///< section pixel size; required (areas in mm^2)
};

/// Where a section's atlas slice sits in the CCF: the stack and slice the atlas file belongs to.
struct StackSliceRef {
    AtlasStack stack;
    int index = 0;
    bool ccf = false; ///< the stack was cut from a volume (CCF micrometres), not the built-in
};

/// The stack slice that `atlasFile` is (a slice-NNN.tif beside a manifest.json), or nullopt.
std::optional<StackSliceRef> stackSliceOf(const std::filesystem::path& atlasFile);

struct SectionCellCounts {
    pipeline::CellTable table;
    std::string countsCsv, cellsCsv;
    double diameterPx = 0;
};

/// Detects and counts. `ontology` may be empty (no roll-up; names from `slice`'s stack when
/// given). \return InvalidArgument (pixel size or diameter out of range, channel not in the
/// image, a diameter under 2 px), the errors of detectCells and countCells.
[[nodiscard]] core::Result<SectionCellCounts>
countSectionCells(const cv::Mat& section, const pipeline::Registration& registration,
                  const cv::Mat& atlasLabels, const core::Ontology& ontology,
                  const std::optional<StackSliceRef>& slice, const CellCountOptions& options);

/// Sums COUNTS.csv files (of the sections of a run) by id into one table of the same columns
/// (density recomputed). \return the errors of reading and parsing (the message names the file).
[[nodiscard]] core::Result<std::string>
sumCountsCsv(const std::vector<std::filesystem::path>& countsFiles);

/// The daemon's counting of one registered section (the registration worker, after the
/// registration is journaled; docs/cells.md): reads the section image and the atlas slice, loads
/// `ontologyFile` when given, counts, writes `<base>.counts.csv` and `<base>.cells.csv`
/// atomically, then the run's totals (writeRunCounts of `runDir`).
struct CellCountJob {
    std::filesystem::path image, atlas; ///< the section image; the atlas slice registered to
    std::filesystem::path base;         ///< outputs: base + ".counts.csv" / ".cells.csv"
    std::filesystem::path runDir;       ///< the run's folder: run-counts.csv goes there
    std::filesystem::path ontologyFile; ///< empty: no roll-up
    CellCountOptions options;
};
/// CELLS.csv is written before COUNTS.csv, so a COUNTS.csv present means both are complete.
/// \return a summary (counted cells, regions, files written), or the first error.
[[nodiscard]] core::Result<nlohmann::json> countCellsBeside(const pipeline::Registration& reg,
                                                            const CellCountJob& job);

/// Sums the latest attempt of every section's `*-a<N>.counts.csv` under `runDir` (files named
/// `<section id>-<name>-a<attempt>.counts.csv`) into `runDir/run-counts.csv`.
/// \return the errors of sumCountsCsv and of writing.
[[nodiscard]] core::Result<void> writeRunCounts(const std::filesystem::path& runDir);

} // namespace slicestation::daemon
