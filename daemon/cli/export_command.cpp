#include "slicestation/daemon/cli/export_command.hpp"

#include "slicestation/core/atomic_file.hpp"
#include "slicestation/daemon/cli/cli.hpp"
#include "slicestation/daemon/cli/cli_output.hpp"
#include "slicestation/daemon/export/section_export.hpp"

#include <nlohmann/json.hpp>

#include <iostream>
#include <sstream>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;
using nlohmann::json;

namespace {

int writeOut(const std::string& text, const std::string& output) {
    if (output.empty()) {
        std::cout << text;
        return kExitOk;
    }
    if (auto w = core::writeFileAtomically(output, text); !w)
        return reportError("export", w.error());
    return kExitOk;
}

bool safeFileName(const std::string& name) {
    if (name.empty() || name == "." || name == ".." || name.size() > 200)
        return false;
    for (char c : name)
        if (!(std::isalnum(static_cast<unsigned char>(c)) || c == '.' || c == '-' || c == '_'))
            return false;
    return true;
}

} // namespace

int writeRunExport(const std::string& format, const std::string& body, const std::string& output) {
    if (format != "qupath")
        return writeOut(body, output);
    if (output.empty()) {
        std::cerr << "slicectl export: error: --format qupath writes one file per section: give "
                     "--output DIR\n";
        return kExitUsage;
    }
    const json j = json::parse(body, nullptr, false);
    if (j.is_discarded() || !j.is_object() || !j.contains("sections") || !j["sections"].is_array())
        return reportError("export", makeError(ErrorCode::InvalidArgument,
                                               "the daemon's reply is not a QuPath export"));
    std::error_code ec;
    std::filesystem::create_directories(output, ec);
    if (ec)
        return reportError("export", makeError(ErrorCode::IoError,
                                               "cannot create " + output + ": " + ec.message()));
    Progress progress("export");
    progress.phase("writing GeoJSON", int(j["sections"].size()));
    json index = json::array();
    int done = 0;
    for (const json& s : j["sections"]) {
        const std::string file = s.value("file", std::string());
        // The daemon builds the names from ids and plan names; still, never a path.
        if (!safeFileName(file) || !s.contains("feature_collection"))
            return reportError("export",
                               makeError(ErrorCode::InvalidArgument,
                                         "the daemon's reply names a bad file \"" + file + "\""));
        const std::filesystem::path path = std::filesystem::path(output) / file;
        if (auto w = core::writeFileAtomically(path, s["feature_collection"].dump() + "\n"); !w)
            return reportError("export", w.error());
        json entry = s;
        entry.erase("feature_collection");
        index.push_back(std::move(entry));
        progress.advance(++done);
    }
    json run{{"run_id", j.value("run_id", 0)}, {"sections", index}};
    if (j.contains("skipped"))
        run["skipped"] = j["skipped"];
    if (auto w = core::writeFileAtomically(std::filesystem::path(output) / "run.json",
                                           run.dump(2) + "\n");
        !w)
        return reportError("export", w.error());
    std::cout << "wrote " << done << " GeoJSON file" << (done == 1 ? "" : "s") << " to " << output
              << "\n";
    if (j.contains("skipped"))
        std::cout << "skipped: " << j["skipped"].get<std::string>() << "\n";
    return kExitOk;
}

int exportResultFile(const std::string& format, const std::filesystem::path& result,
                     const std::string& output) {
    if (format == "json") {
        std::cerr << "slicectl export: error: --result: the result is JSON already; choose csv, "
                     "quicknii or qupath\n";
        return kExitUsage;
    }
    auto files = readResultFile(result);
    if (!files)
        return reportError("export", files.error());
    if (format == "quicknii") {
        const json& image = files->result.value("image", json::object());
        std::string name = image.value("file", image.value("path", std::string()));
        name = std::filesystem::path(name).filename().string();
        auto slice = quickNiiSliceOfResult(*files, name, 1);
        if (!slice)
            return reportError("export", slice.error());
        return writeOut(
            quickNiiSeries(result.stem().string(), json::array({*slice})).dump(1) + "\n", output);
    }
    if (format == "qupath") {
        auto fc = qupathOfResult(*files);
        if (!fc)
            return reportError("export", fc.error());
        return writeOut(fc->dump() + "\n", output);
    }
    // csv: the mapped points.
    const json& pts = files->result.value("points", json::array());
    std::ostringstream os;
    os << "x,y,atlas_x,atlas_y,ccf_x_um,ccf_y_um,ccf_z_um\n";
    for (const json& p : pts) {
        os << plainNumber(p.value("x", 0.0)) << ',' << plainNumber(p.value("y", 0.0)) << ','
           << plainNumber(p.value("atlas_x", 0.0)) << ',' << plainNumber(p.value("atlas_y", 0.0));
        if (p.contains("ccf_um") && p["ccf_um"].is_array() && p["ccf_um"].size() == 3)
            for (const json& c : p["ccf_um"])
                os << ',' << plainNumber(c.get<double>());
        else
            os << ",,,";
        os << "\n";
    }
    return writeOut(os.str(), output);
}

} // namespace slicestation::daemon
