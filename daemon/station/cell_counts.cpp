#include "slicestation/daemon/station/cell_counts.hpp"

#include "slicestation/core/atomic_file.hpp"
#include "slicestation/core/csv.hpp"
#include "slicestation/core/image_file.hpp"
#include "slicestation/pipeline/atlas.hpp"

#include <opencv2/imgproc.hpp>

#include <cmath>
#include <fstream>
#include <map>
#include <sstream>

namespace slicestation::daemon {
namespace {

using core::ErrorCode;
using core::makeError;

/// RFC 4180: quote a field holding a comma, a quote or a line break.
std::string csvField(const std::string& s) {
    if (s.find_first_of(",\"\r\n") == std::string::npos)
        return s;
    std::string out = "\"";
    for (char c : s) {
        if (c == '"')
            out += '"';
        out += c;
    }
    return out + "\"";
}

std::string number(double v, int precision = 6) {
    std::ostringstream os;
    os.precision(precision);
    os << v;
    return os.str();
}

struct Names {
    std::string acronym, name;
};

Names namesOf(std::uint32_t id, const core::Ontology& onto,
              const std::optional<StackSliceRef>& slice) {
    if (const core::Structure* s = onto.find(id))
        return {s->acronym, s->name};
    if (slice)
        if (const StackRegion* r = findRegion(slice->stack, id))
            return {r->acronym, r->name};
    return {};
}

constexpr const char* kCountsHeader =
    "id,acronym,name,parent_id,depth,count,area_mm2,density_per_mm2\n";

std::string countsRow(std::uint32_t id, const Names& n, std::uint32_t parent, int depth,
                      std::int64_t count, double areaMm2) {
    return std::to_string(id) + "," + csvField(n.acronym) + "," + csvField(n.name) + "," +
           (parent ? std::to_string(parent) : std::string()) + "," + std::to_string(depth) + "," +
           std::to_string(count) + "," + number(areaMm2) + "," +
           (areaMm2 > 0 ? number(double(count) / areaMm2) : std::string()) + "\n";
}

} // namespace

std::optional<StackSliceRef> stackSliceOf(const std::filesystem::path& atlasFile) {
    std::error_code ec;
    const auto dir = atlasFile.parent_path();
    if (!std::filesystem::exists(dir / "manifest.json", ec))
        return std::nullopt;
    auto stack = readStack(dir);
    if (!stack)
        return std::nullopt;
    for (const StackSlice& s : stack->slices)
        if (std::filesystem::path(s.file).filename() == atlasFile.filename()) {
            StackSliceRef ref;
            ref.index = s.index;
            ref.ccf = stack->source.value("kind", std::string()) == "volume";
            ref.stack = std::move(*stack);
            return ref;
        }
    return std::nullopt;
}

core::Result<SectionCellCounts>
countSectionCells(const cv::Mat& section, const pipeline::Registration& reg, const cv::Mat& labels,
                  const core::Ontology& ontology, const std::optional<StackSliceRef>& slice,
                  const CellCountOptions& o) {
    if (!(o.imageUmPerPx >= 0.01 && o.imageUmPerPx <= 1000))
        return makeError(ErrorCode::InvalidArgument,
                         "cell counting needs the section's pixel size (--image-um-per-px, "
                         "0.01 to 1000 um), not " +
                             number(o.imageUmPerPx));
    if (!(o.cellDiameterUm >= 1 && o.cellDiameterUm <= 500))
        return makeError(ErrorCode::InvalidArgument,
                         "cell diameter must be 1 to 500 um, not " + number(o.cellDiameterUm));
    SectionCellCounts out;
    out.diameterPx = o.cellDiameterUm / o.imageUmPerPx;
    if (out.diameterPx < 2 || out.diameterPx > 200)
        return makeError(ErrorCode::InvalidArgument,
                         "cells of " + number(o.cellDiameterUm) + " um are " +
                             number(out.diameterPx, 3) + " px at " + number(o.imageUmPerPx) +
                             " um/px: the detector needs 2 to 200 px (image the section finer, "
                             "or count on a reduced copy)");
    pipeline::CellDetectorOptions d = o.detector;
    d.diameterPx = out.diameterPx;
    try {
        cv::resize(reg.workingTissueMask, d.mask, section.size(), 0, 0, cv::INTER_NEAREST);
    } catch (const cv::Exception& e) {
        return makeError(ErrorCode::Internal, std::string("cell counting: OpenCV: ") + e.what());
    }
    auto found = pipeline::detectCells(section, d);
    if (!found)
        return found.error();
    auto table = pipeline::countCells(reg, labels, *found, ontology);
    if (!table)
        return table.error();
    out.table = std::move(*table);

    const double mm2PerPx = o.imageUmPerPx * o.imageUmPerPx * 1e-6;
    std::string counts = kCountsHeader;
    for (const pipeline::RegionCount& r : out.table.regions)
        counts += countsRow(r.id, namesOf(r.id, ontology, slice), r.parentId, r.depth, r.cells,
                            r.areaPx * mm2PerPx);
    out.countsCsv = std::move(counts);

    std::string cells =
        "x,y,ccf_x_um,ccf_y_um,ccf_z_um,id,acronym,atlas_x,atlas_y,excluded,cells\n";
    const pipeline::SliceGeometry* geometry =
        slice && slice->ccf && slice->index >= 0 &&
                size_t(slice->index) < slice->stack.slices.size()
            ? &slice->stack.slices[size_t(slice->index)].geometry
            : nullptr;
    for (const pipeline::MappedCell& c : out.table.cells) {
        std::string ccf = ",,";
        if (geometry) {
            const cv::Vec3d um = geometry->atlasUm(c.atlasPx.x, c.atlasPx.y);
            ccf = number(um[0], 7) + "," + number(um[1], 7) + "," + number(um[2], 7);
        }
        cells += number(c.imagePx.x, 7) + "," + number(c.imagePx.y, 7) + "," + ccf + "," +
                 std::to_string(c.atlasId) + "," +
                 csvField(namesOf(std::uint32_t(c.atlasId), ontology, slice).acronym) + "," +
                 number(c.atlasPx.x, 7) + "," + number(c.atlasPx.y, 7) + "," +
                 (c.excluded ? "1" : "0") + "," + std::to_string(c.cells) + "\n";
    }
    out.cellsCsv = std::move(cells);
    return out;
}

core::Result<std::string> sumCountsCsv(const std::vector<std::filesystem::path>& files) {
    struct Row {
        std::string acronym, name, parent;
        int depth = 0;
        std::int64_t count = 0;
        double area = 0;
    };
    std::map<std::uint32_t, Row> rows;
    for (const auto& f : files) {
        std::ifstream in(f, std::ios::binary);
        if (!in)
            return makeError(ErrorCode::NotFound, "cannot read " + f.string());
        std::ostringstream text;
        text << in.rdbuf();
        auto recs = core::parseCsv(text.str(), f.string());
        if (!recs)
            return recs.error();
        if (recs->empty() || recs->front().fields.size() < 8 || recs->front().fields[0] != "id" ||
            recs->front().fields[5] != "count" || recs->front().fields[6] != "area_mm2")
            return makeError(ErrorCode::InvalidArgument,
                             f.string() + ": not a COUNTS.csv (header id,...,count,area_mm2)");
        for (size_t i = 1; i < recs->size(); ++i) {
            const auto& fl = (*recs)[i].fields;
            if (fl.size() < 8)
                return makeError(ErrorCode::InvalidArgument, f.string() + ": line " +
                                                                 std::to_string((*recs)[i].line) +
                                                                 ": expected 8 fields");
            try {
                const auto id = std::uint32_t(std::stoul(fl[0]));
                Row& r = rows[id];
                if (r.acronym.empty() && r.name.empty()) {
                    r.acronym = fl[1];
                    r.name = fl[2];
                    r.parent = fl[3];
                    r.depth = std::stoi(fl[4]);
                }
                r.count += std::stoll(fl[5]);
                r.area += std::stod(fl[6]);
            } catch (const std::exception&) {
                return makeError(ErrorCode::InvalidArgument, f.string() + ": line " +
                                                                 std::to_string((*recs)[i].line) +
                                                                 ": a number is malformed");
            }
        }
    }
    std::string out = kCountsHeader;
    for (const auto& [id, r] : rows)
        out += std::to_string(id) + "," + csvField(r.acronym) + "," + csvField(r.name) + "," +
               r.parent + "," + std::to_string(r.depth) + "," + std::to_string(r.count) + "," +
               number(r.area) + "," + (r.area > 0 ? number(double(r.count) / r.area) : "") + "\n";
    return out;
}

core::Result<nlohmann::json> countCellsBeside(const pipeline::Registration& reg,
                                              const CellCountJob& job) {
    auto section = core::readImage(job.image);
    if (!section)
        return section.error();
    auto atlasImage = core::readImage(job.atlas);
    if (!atlasImage)
        return atlasImage.error();
    auto labels = pipeline::labelsFromImage(*atlasImage);
    if (!labels)
        return labels.error();
    auto ontologyRead = core::readOntologyCsvIfGiven(job.ontologyFile);
    if (!ontologyRead)
        return ontologyRead.error();
    const core::Ontology& ontology = *ontologyRead;
    auto counts =
        countSectionCells(*section, reg, *labels, ontology, stackSliceOf(job.atlas), job.options);
    if (!counts)
        return counts.error();
    const std::filesystem::path countsFile = job.base.string() + ".counts.csv";
    const std::filesystem::path cellsFile = job.base.string() + ".cells.csv";
    if (auto w = core::writeFileAtomically(cellsFile, counts->cellsCsv); !w)
        return w.error();
    if (auto w = core::writeFileAtomically(countsFile, counts->countsCsv); !w)
        return w.error();
    std::int64_t counted = 0;
    for (const auto& c : counts->table.cells)
        if (!c.excluded && c.atlasId > 0)
            counted += c.cells;
    nlohmann::json out{{"counted", counted},
                       {"excluded_in_damage", counts->table.excludedCells},
                       {"regions", counts->table.regions.size()},
                       {"counts", countsFile.filename().string()},
                       {"cells", cellsFile.filename().string()}};
    if (!job.runDir.empty()) {
        if (auto r = writeRunCounts(job.runDir); !r)
            return r.error();
        out["run_counts"] = "run-counts.csv";
    }
    return out;
}

core::Result<void> writeRunCounts(const std::filesystem::path& runDir) {
    // Latest attempt per section: a rescan replaces the section's earlier counts.
    std::map<std::string, std::pair<int, std::filesystem::path>> latest;
    std::error_code ec;
    for (auto it = std::filesystem::recursive_directory_iterator(runDir, ec);
         !ec && it != std::filesystem::recursive_directory_iterator(); it.increment(ec)) {
        const std::string name = it->path().filename().string();
        const std::string suffix = ".counts.csv";
        if (name.size() <= suffix.size() ||
            name.compare(name.size() - suffix.size(), suffix.size(), suffix) != 0)
            continue;
        const std::string stem = name.substr(0, name.size() - suffix.size());
        const auto a = stem.rfind("-a");
        const auto dash = stem.find('-');
        if (a == std::string::npos || dash == std::string::npos || a + 2 >= stem.size())
            continue;
        int attempt = 0;
        try {
            attempt = std::stoi(stem.substr(a + 2));
        } catch (const std::exception&) {
            continue;
        }
        const std::string key =
            it->path().parent_path().string() + "/" + stem.substr(0, dash); // section id
        auto& slot = latest[key];
        if (slot.second.empty() || attempt > slot.first)
            slot = {attempt, it->path()};
    }
    if (ec)
        return makeError(ErrorCode::IoError,
                         "cannot list " + runDir.string() + ": " + ec.message());
    std::vector<std::filesystem::path> files;
    for (const auto& [key, v] : latest)
        files.push_back(v.second);
    auto sum = sumCountsCsv(files);
    if (!sum)
        return sum.error();
    return core::writeFileAtomically(runDir / "run-counts.csv", *sum);
}

} // namespace slicestation::daemon
