#include "slicestation/daemon/export/run_export.hpp"

#include "slicestation/daemon/export/section_export.hpp"

#include <cctype>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;
using nlohmann::json;

namespace {

/// A file name from names the plan gave: letters, digits, '.', '-', '_' kept, others '_'. The
/// section id leads, so two sections never share a file.
std::string safeName(std::string s) {
    for (char& ch : s)
        if (!(std::isalnum(static_cast<unsigned char>(ch)) || ch == '.' || ch == '-' || ch == '_'))
            ch = '_';
    return s;
}

} // namespace

bool isResultExportFormat(const std::string& format) {
    return format == "quicknii" || format == "qupath";
}

core::Result<std::string> exportRunResults(Journal& journal, const std::filesystem::path& stateDir,
                                           std::int64_t runId, const std::string& format) {
    if (!isResultExportFormat(format))
        return makeError(ErrorCode::InvalidArgument,
                         "format: expected quicknii or qupath, got \"" + format + "\"");
    auto run = journal.run(runId);
    if (!run)
        return run.error();
    auto sections = journal.sections(runId);
    if (!sections)
        return sections.error();
    json slices = json::array(), collections = json::array();
    std::string skipped;
    int nr = 0;
    for (const SectionRecord& s : *sections) {
        ++nr;
        auto caps = journal.captures(s.id);
        auto regs = journal.registrations(s.id);
        if (!caps || !regs || caps->empty())
            continue;
        const CaptureRecord& c = caps->back();
        const RegistrationRecord* reg = nullptr;
        for (const RegistrationRecord& r : *regs)
            if (r.captureId == c.id)
                reg = &r;
        if (!reg)
            continue;
        const SectionFiles files{reg->result, (stateDir / reg->resultPath).parent_path()};
        const std::string image = std::filesystem::path(c.imagePath).filename().string();
        if (format == "quicknii") {
            auto slice = quickNiiSliceOfResult(files, image, nr);
            if (!slice) {
                if (slice.error().code == ErrorCode::InvalidArgument &&
                    slice.error().message.find("CCF") != std::string::npos)
                    return slice.error(); // the whole run's atlas: nothing can be exported
                skipped += " " + s.name + " (" + slice.error().message + ")";
                continue;
            }
            slices.push_back(std::move(*slice));
        } else {
            auto fc = qupathOfResult(files);
            if (!fc) {
                skipped += " " + s.name + " (" + fc.error().message + ")";
                continue;
            }
            collections.push_back(
                {{"section_id", s.id},
                 {"slide", s.slideName},
                 {"section", s.name},
                 {"image", c.imagePath},
                 {"file",
                  safeName(std::to_string(s.id) + "_" + s.slideName + "_" + s.name) + ".geojson"},
                 {"feature_collection", std::move(*fc)}});
        }
    }
    if (slices.empty() && collections.empty())
        return makeError(ErrorCode::NotFound, "run " + std::to_string(runId) +
                                                  " has no registered section to export" +
                                                  (skipped.empty() ? "" : ":" + skipped));
    json out = format == "quicknii" ? quickNiiSeries(run->name, std::move(slices))
                                    : json{{"run_id", runId}, {"sections", collections}};
    if (!skipped.empty())
        out["skipped"] = skipped.substr(1);
    return out.dump(1) + "\n";
}

} // namespace slicestation::daemon
