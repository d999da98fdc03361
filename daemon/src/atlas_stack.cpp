#include "slicestation/daemon/atlas_stack.hpp"

#include "slicestation/core/image_file.hpp"
#include "slicestation/daemon/register_command.hpp"
#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/sim/builtin_atlas.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <sstream>

namespace slicestation::daemon {
namespace {

using core::ErrorCode;
using core::makeError;
using nlohmann::json;
namespace fs = std::filesystem;

json vec(const cv::Vec3d& v) { return json::array({v[0], v[1], v[2]}); }

/// Reads field `key` of `j` as T, or an error naming the manifest and the field.
template <class T>
core::Result<T> field(const json& j, const char* key, const fs::path& manifest,
                      const std::string& where) {
    const auto it = j.find(key);
    if (it == j.end())
        return makeError(ErrorCode::InvalidArgument,
                         manifest.string() + ": " + where + " has no field '" + key + "'");
    try {
        return it->get<T>();
    } catch (const json::exception&) {
        return makeError(ErrorCode::InvalidArgument,
                         manifest.string() + ": " + where + "." + key + " has the wrong type");
    }
}

core::Result<cv::Vec3d> vecField(const json& j, const char* key, const fs::path& manifest,
                                 const std::string& where) {
    auto a = field<std::vector<double>>(j, key, manifest, where);
    if (!a) return a.error();
    if (a->size() != 3)
        return makeError(ErrorCode::InvalidArgument,
                         manifest.string() + ": " + where + "." + key + " must have 3 numbers");
    return cv::Vec3d((*a)[0], (*a)[1], (*a)[2]);
}

} // namespace

std::string colorHex(std::uint32_t rgb) {
    char buf[8];
    std::snprintf(buf, sizeof buf, "#%06X", rgb & 0xFFFFFFu);
    return buf;
}

const StackRegion* findRegion(const AtlasStack& stack, std::uint32_t id) noexcept {
    if (id == 0) return nullptr;
    const auto it = std::find_if(stack.regions.begin(), stack.regions.end(),
                                 [id](const StackRegion& r) { return r.id == id; });
    return it == stack.regions.end() ? nullptr : &*it;
}

core::Result<AtlasStack> writeStack(const fs::path& dir,
                                    const std::vector<pipeline::AtlasSlice>& slices,
                                    std::vector<StackRegion> regions, json source) {
    if (slices.empty()) return makeError(ErrorCode::InvalidArgument, "the stack has no slices");
    std::error_code ec;
    fs::create_directories(dir, ec);
    if (ec) return makeError(ErrorCode::IoError, "cannot create " + dir.string(), ec.value());
    AtlasStack stack;
    stack.dir = dir;
    json js = json::array();
    for (size_t i = 0; i < slices.size(); ++i) {
        char name[32];
        std::snprintf(name, sizeof name, "slice-%03zu.tif", i);
        if (auto w = core::writeImage(dir / name, slices[i].labels); !w) return w.error();
        const pipeline::SliceGeometry& g = slices[i].geometry;
        StackSlice s{int(i), name, g.positionUm, cv::norm(g.columnUm), g};
        js.push_back({{"index", s.index},
                      {"file", s.file},
                      {"position_um", s.positionUm},
                      {"normal", vec(g.normal)},
                      {"um_per_px", s.umPerPx},
                      {"width", g.size.width},
                      {"height", g.size.height},
                      {"origin_um", vec(g.originUm)},
                      {"column_um", vec(g.columnUm)},
                      {"row_um", vec(g.rowUm)}});
        stack.slices.push_back(std::move(s));
    }
    json jr = json::array();
    for (const StackRegion& r : regions)
        jr.push_back({{"id", r.id}, {"name", r.name}, {"acronym", r.acronym},
                      {"color", colorHex(r.colorRgb)}});
    source["frame"] = "micrometres along (AP, DV, LR) from the centre of the first voxel";
    const json manifest = {{"slices", js}, {"regions", jr}, {"source", source}};
    if (auto w = writeFileAtomically(dir / "manifest.json", manifest.dump(2) + "\n"); !w)
        return w.error();
    stack.regions = std::move(regions);
    stack.source = std::move(source);
    return stack;
}

core::Result<AtlasStack> readStack(const fs::path& dirOrManifest) {
    const bool isFile = dirOrManifest.filename() == "manifest.json" ||
                        (fs::exists(dirOrManifest) && !fs::is_directory(dirOrManifest));
    const fs::path manifest = isFile ? dirOrManifest : dirOrManifest / "manifest.json";
    if (!fs::exists(manifest))
        return makeError(ErrorCode::NotFound, "no atlas stack manifest at " + manifest.string());
    std::ifstream in(manifest);
    if (!in) return makeError(ErrorCode::IoError, "cannot read " + manifest.string());
    json j;
    try {
        j = json::parse(in);
    } catch (const json::exception& e) {
        return makeError(ErrorCode::InvalidArgument,
                         manifest.string() + ": not valid JSON (" + e.what() + ")");
    }
    if (!j.is_object() || !j.contains("slices") || !j["slices"].is_array() || j["slices"].empty())
        return makeError(ErrorCode::InvalidArgument,
                         manifest.string() + ": 'slices' must be a non-empty array");
    AtlasStack stack;
    stack.dir = manifest.parent_path();
    for (size_t i = 0; i < j["slices"].size(); ++i) {
        const json& e = j["slices"][i];
        const std::string where = "slices[" + std::to_string(i) + "]";
        auto index = field<int>(e, "index", manifest, where);
        if (!index) return index.error();
        if (*index != int(i))
            return makeError(ErrorCode::InvalidArgument,
                             manifest.string() + ": " + where + ".index must be " +
                                 std::to_string(i) + " (slices in index order)");
        auto file = field<std::string>(e, "file", manifest, where);
        auto pos = field<double>(e, "position_um", manifest, where);
        auto um = field<double>(e, "um_per_px", manifest, where);
        auto normal = vecField(e, "normal", manifest, where);
        if (!file) return file.error();
        if (!pos) return pos.error();
        if (!um) return um.error();
        if (!normal) return normal.error();
        if (!(*um > 0))
            return makeError(ErrorCode::InvalidArgument,
                             manifest.string() + ": " + where + ".um_per_px must be positive");
        StackSlice s;
        s.index = *index;
        s.file = *file;
        s.positionUm = *pos;
        s.umPerPx = *um;
        s.geometry.positionUm = *pos;
        s.geometry.normal = *normal;
        // The in-plane frame is optional (a hand-made stack may not know it).
        if (e.contains("origin_um")) {
            auto o = vecField(e, "origin_um", manifest, where);
            auto c = vecField(e, "column_um", manifest, where);
            auto r = vecField(e, "row_um", manifest, where);
            if (!o) return o.error();
            if (!c) return c.error();
            if (!r) return r.error();
            s.geometry.originUm = *o;
            s.geometry.columnUm = *c;
            s.geometry.rowUm = *r;
        }
        s.geometry.size = cv::Size(e.value("width", 0), e.value("height", 0));
        stack.slices.push_back(std::move(s));
    }
    if (j.contains("regions") && j["regions"].is_array()) {
        for (size_t i = 0; i < j["regions"].size(); ++i) {
            const json& e = j["regions"][i];
            const std::string where = "regions[" + std::to_string(i) + "]";
            auto id = field<std::uint32_t>(e, "id", manifest, where);
            if (!id) return id.error();
            StackRegion r{*id, e.value("name", ""), e.value("acronym", ""), 0};
            const std::string color = e.value("color", "#000000");
            r.colorRgb = std::uint32_t(std::strtoul(color.c_str() + (color[0] == '#'), nullptr, 16));
            stack.regions.push_back(std::move(r));
        }
    }
    stack.source = j.value("source", json::object());
    return stack;
}

core::Result<fs::path> stackSlicePath(const AtlasStack& stack, int index) {
    if (index < 0 || index >= int(stack.slices.size()))
        return makeError(ErrorCode::OutOfRange,
                         "slice " + std::to_string(index) + " is not in the stack at " +
                             stack.dir.string() + " (0.." +
                             std::to_string(int(stack.slices.size()) - 1) + ")");
    return stack.dir / stack.slices[size_t(index)].file;
}

core::Result<cv::Mat> readStackSlice(const AtlasStack& stack, int index) {
    auto path = stackSlicePath(stack, index);
    if (!path) return path.error();
    auto image = core::readImage(*path);
    if (!image) return image.error();
    // A plane beyond the brain's ends is all outside: a valid slice with no labels.
    if (image->channels() == 1 && image->depth() != CV_32F && cv::countNonZero(*image) == 0)
        return cv::Mat(cv::Mat::zeros(image->size(), CV_32S));
    auto labels = pipeline::labelsFromImage(*image);
    if (!labels)
        return makeError(labels.error().code, path->string() + ": " + labels.error().message);
    return labels;
}

core::Result<std::vector<pipeline::AtlasSlice>> builtinStackSlices(double intervalUm,
                                                                   double firstUm) {
    if (!(intervalUm > 0) || !std::isfinite(intervalUm))
        return makeError(ErrorCode::InvalidArgument, "interval_um must be a positive number");
    if (!(firstUm >= 0 && firstUm <= kBuiltinLengthUm))
        return makeError(ErrorCode::OutOfRange,
                         "first_um " + std::to_string(firstUm) +
                             " is outside the built-in brain (0.." +
                             std::to_string(int(kBuiltinLengthUm)) + " um)");
    std::vector<pipeline::AtlasSlice> slices;
    for (int i = 0;; ++i) {
        const double pos = firstUm + i * intervalUm;
        if (pos > kBuiltinLengthUm + 1e-6) break;
        pipeline::AtlasSlice s;
        s.labels = sim::builtinAtlasPlane(pos / kBuiltinLengthUm);
        // The built-in planes are coronal: rows DV, columns LR, centred on the brain's axis.
        pipeline::SliceGeometry& g = s.geometry;
        g.size = s.labels.size();
        g.positionUm = pos;
        g.normal = {1, 0, 0};
        g.columnUm = {0, 0, kBuiltinUmPerPx};
        g.rowUm = {0, kBuiltinUmPerPx, 0};
        g.originUm = {pos, 0, 0};
        slices.push_back(std::move(s));
    }
    return slices;
}

std::vector<StackRegion> builtinStackRegions() {
    std::vector<StackRegion> out;
    for (const sim::RegionInfo& r : sim::builtinRegions())
        out.push_back({std::uint32_t(r.id), r.name, r.acronym, r.colorRgb});
    return out;
}

} // namespace slicestation::daemon
