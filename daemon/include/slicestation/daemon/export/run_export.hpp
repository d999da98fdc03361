#pragma once
/// A run's sections exported for QuickNII/VisuAlign and QuPath, from the journal and the result
/// files under the state directory (docs/results.md). Blocking file I/O; re-entrant (reads only).
#include "slicestation/core/result.hpp"
#include "slicestation/daemon/storage/journal.hpp"

#include <cstdint>
#include <filesystem>
#include <string>

namespace slicestation::daemon {

/// The formats of exportRunResults.
bool isResultExportFormat(const std::string& format);

/// "quicknii": one QuickNII/VisuAlign series (quickNiiSeries) with a slice per registered
/// section (latest capture), nr = the section's place in the run (1-based);
/// "qupath": {"run_id", "sections": [{"section_id", "slide", "section", "image", "file",
/// "feature_collection"}]}, one GeoJSON FeatureCollection per registered section.
/// \return the JSON text; NotFound (no such run, or no section of it registered with a saved
/// mapping), InvalidArgument (an unknown format; quicknii for an atlas not cut from a CCF volume),
/// the errors of reading the journal and the files.
[[nodiscard]] core::Result<std::string> exportRunResults(Journal& journal,
                                                         const std::filesystem::path& stateDir,
                                                         std::int64_t runId,
                                                         const std::string& format);

} // namespace slicestation::daemon
