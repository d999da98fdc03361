#pragma once
/// `slicectl export`: a run from the daemon (RUN) or one registration (--result RESULT.json) in
/// the formats of docs/results.md. The daemon's reply is fetched by cli_daemon.cpp; this file
/// writes it and does the one-result export locally. Blocking file I/O.
#include "slicestation/core/result.hpp"

#include <filesystem>
#include <string>

namespace slicestation::daemon {

/// Writes a run's export as the daemon sent it (`body`): csv, json and quicknii to `output` (a
/// file; stdout when empty); qupath into the directory `output` (created; required), one
/// `<section id>_<slide>_<section>.geojson` per section plus `run.json` naming them, with a
/// progress line on a terminal. \return the exit code (0; 1 qupath without --output; 2 a reply
/// that is not the expected JSON or a file that cannot be written).
int writeRunExport(const std::string& format, const std::string& body, const std::string& output);

/// One registration's export from its result.json and the files beside it: quicknii (a series
/// of one slice, `nr` 1), qupath (one FeatureCollection), csv (the points: x, y, atlas_x,
/// atlas_y and ccf_x_um, ccf_y_um, ccf_z_um when the atlas is a CCF slice). Written to `output`
/// (stdout when empty). \return the exit code: 0, 1 (json asked: result.json is that already),
/// 2 (the result or its files are missing or malformed; quicknii for a non-CCF atlas).
int exportResultFile(const std::string& format, const std::filesystem::path& result,
                     const std::string& output);

} // namespace slicestation::daemon
