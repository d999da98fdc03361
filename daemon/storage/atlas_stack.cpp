#include "slicestation/daemon/storage/atlas_stack.hpp"

#include "slicestation/pipeline/atlas_matching.hpp"

#include "slicestation/core/atomic_file.hpp"

#include "slicestation/core/image_file.hpp"
#include "slicestation/daemon/cli/register_command.hpp"
#include "slicestation/daemon/config/config_document.hpp"
#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/sim/builtin_atlas.hpp"

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <fstream>
#include <limits>
#include <sstream>

namespace slicestation::daemon {
namespace {

using core::ErrorCode;
using core::makeError;
using nlohmann::json;
namespace fs = std::filesystem;

json vec(const cv::Vec3d& v) {
    return json::array({v[0], v[1], v[2]});
}

/// Bounds of the manifest's fields: a hand-edited or damaged manifest must give a clear error,
/// never an exception or a slice size nobody can allocate.
constexpr std::uintmax_t kMaxManifestBytes = std::uintmax_t{64} << 20;
constexpr double kMaxCoordinateUm = 1e7; ///< positions and frame vectors: 10 m
constexpr std::int64_t kMaxSliceSidePx = 1 << 16;
constexpr std::size_t kMaxVentricleIds = 4096;

/// A 3-vector of finite numbers within +-kMaxCoordinateUm.
core::Result<cv::Vec3d> vecField(const FieldReader& rd, const json& obj, const std::string& path,
                                 const char* key) {
    const std::string field = FieldReader::join(path, key);
    if (!obj.contains(key))
        return rd.bad(field, "missing");
    const json& a = obj[key];
    if (!a.is_array() || a.size() != 3)
        return rd.bad(field, "expected an array of 3 numbers");
    cv::Vec3d v;
    for (int i = 0; i < 3; ++i) {
        // FieldReader reads object members; an array element is checked here alike.
        const json& e = a[size_t(i)];
        if (!e.is_number() || !std::isfinite(e.get<double>()) ||
            std::abs(e.get<double>()) > kMaxCoordinateUm)
            return rd.bad(field + "[" + std::to_string(i) + "]",
                          "expected a finite number within +-1e7, got " + e.dump());
        v[i] = e.get<double>();
    }
    return v;
}

/// A slice file name (member `key`): relative, inside the stack directory, a plain name.
core::Result<std::string> sliceFile(const FieldReader& rd, const json& obj, const std::string& path,
                                    const char* key = "file") {
    auto file = rd.string(obj, path, key, std::nullopt);
    if (!file)
        return file.error();
    const fs::path p(*file);
    const bool plain = !file->empty() && file->size() <= 255 && p.is_relative() &&
                       std::none_of(p.begin(), p.end(), [](const fs::path& part) {
                           return part == ".." || part == ".";
                       });
    if (!plain)
        return rd.bad(FieldReader::join(path, key),
                      "'" + file->substr(0, 80) +
                          "' is not a relative file name inside the stack directory");
    return file;
}

core::Result<StackSlice> sliceEntry(const FieldReader& rd, const json& e, size_t i) {
    const std::string where = "slices[" + std::to_string(i) + "]";
    if (!e.is_object())
        return rd.bad(where, "expected an object");
    auto index = rd.integer(e, where, "index", std::nullopt, std::int64_t(i), std::int64_t(i));
    if (!index)
        return index.error();
    auto file = sliceFile(rd, e, where);
    if (!file)
        return file.error();
    auto pos =
        rd.number(e, where, "position_um", std::nullopt, -kMaxCoordinateUm, kMaxCoordinateUm);
    if (!pos)
        return pos.error();
    auto um = rd.number(e, where, "um_per_px", std::nullopt, kMinUmPerPx, kMaxUmPerPx);
    if (!um)
        return um.error();
    auto normal = vecField(rd, e, where, "normal");
    if (!normal)
        return normal.error();
    auto width = rd.integer(e, where, "width", 0, 0, kMaxSliceSidePx);
    if (!width)
        return width.error();
    auto height = rd.integer(e, where, "height", 0, 0, kMaxSliceSidePx);
    if (!height)
        return height.error();
    StackSlice s;
    s.index = int(*index);
    s.file = *file;
    s.positionUm = *pos;
    s.umPerPx = *um;
    s.geometry.positionUm = *pos;
    s.geometry.normal = *normal;
    s.geometry.size = cv::Size(int(*width), int(*height));
    // The atlas intensity plane is optional (stacks cut without --template have none).
    if (e.contains("template")) {
        auto t = sliceFile(rd, e, where, "template");
        if (!t)
            return t.error();
        s.templateFile = *t;
    }
    // So is the plane of every id (major-region stacks cut since it was kept).
    if (e.contains("ids")) {
        auto ids = sliceFile(rd, e, where, "ids");
        if (!ids)
            return ids.error();
        s.idsFile = *ids;
    }
    // The in-plane frame is optional (a hand-made stack may not know it).
    if (e.contains("origin_um")) {
        auto o = vecField(rd, e, where, "origin_um");
        if (!o)
            return o.error();
        auto c = vecField(rd, e, where, "column_um");
        if (!c)
            return c.error();
        auto r = vecField(rd, e, where, "row_um");
        if (!r)
            return r.error();
        s.geometry.originUm = *o;
        s.geometry.columnUm = *c;
        s.geometry.rowUm = *r;
    }
    return s;
}

core::Result<StackRegion> regionEntry(const FieldReader& rd, const json& e, size_t i) {
    const std::string where = "regions[" + std::to_string(i) + "]";
    if (!e.is_object())
        return rd.bad(where, "expected an object");
    auto id =
        rd.integer(e, where, "id", std::nullopt, 0, std::numeric_limits<std::uint32_t>::max());
    if (!id)
        return id.error();
    auto name = rd.string(e, where, "name", "");
    if (!name)
        return name.error();
    auto acronym = rd.string(e, where, "acronym", "");
    if (!acronym)
        return acronym.error();
    auto color = rd.string(e, where, "color", "#000000");
    if (!color)
        return color.error();
    const bool hex = color->size() == 7 && (*color)[0] == '#' &&
                     std::all_of(color->begin() + 1, color->end(),
                                 [](unsigned char c) { return std::isxdigit(c) != 0; });
    if (!hex)
        return rd.bad(where + ".color", "'" + color->substr(0, 20) + "' is not #RRGGBB");
    StackRegion region{std::uint32_t(*id), *name, *acronym,
                       std::uint32_t(std::stoul(color->substr(1), nullptr, 16))};
    // Optional: the ontology path (root first, ending with the id), bounded like the ids.
    if (e.contains("path")) {
        const json& p = e["path"];
        if (!p.is_array() || p.size() > 64)
            return rd.bad(where + ".path", "expected an array of at most 64 ids");
        for (const json& v : p) {
            if (!v.is_number_unsigned() || v.get<std::uint64_t>() > 0xFFFFFFFFull)
                return rd.bad(where + ".path", "expected ids (unsigned 32-bit integers)");
            region.path.push_back(v.get<std::uint32_t>());
        }
        if (!region.path.empty() && region.path.back() != region.id)
            return rd.bad(where + ".path", "must end with the region's own id");
    }
    return region;
}

core::Result<AtlasStack> stackFromJson(const json& j, const fs::path& manifest) {
    const FieldReader rd(manifest.string());
    if (!j.is_object())
        return rd.bad("(top level)", "expected an object");
    if (!j.contains("slices") || !j["slices"].is_array() || j["slices"].empty())
        return rd.bad("slices", "must be a non-empty array");
    const json& slices = j["slices"];
    if (slices.size() > size_t(pipeline::kMaxStackSlices))
        return rd.bad("slices", std::to_string(slices.size()) + " slices, more than the " +
                                    std::to_string(pipeline::kMaxStackSlices) +
                                    " a stack may hold");
    AtlasStack stack;
    stack.dir = manifest.parent_path();
    for (size_t i = 0; i < slices.size(); ++i) {
        auto s = sliceEntry(rd, slices[i], i);
        if (!s)
            return s.error();
        stack.slices.push_back(std::move(*s));
    }
    if (j.contains("regions")) {
        const json& regions = j["regions"];
        if (!regions.is_array())
            return rd.bad("regions", "expected an array");
        for (size_t i = 0; i < regions.size(); ++i) {
            auto r = regionEntry(rd, regions[i], i);
            if (!r)
                return r.error();
            stack.regions.push_back(std::move(*r));
        }
    }
    if (j.contains("ventricle_ids")) {
        const json& v = j["ventricle_ids"];
        if (!v.is_array() || v.size() > kMaxVentricleIds)
            return rd.bad("ventricle_ids", "expected an array of at most " +
                                               std::to_string(kMaxVentricleIds) + " ids");
        for (const json& id : v) {
            if (!id.is_number_unsigned() || id.get<std::uint64_t>() > 0x7FFFFFFFull)
                return rd.bad("ventricle_ids", "expected ids (positive 31-bit integers), got " +
                                                   id.dump().substr(0, 40));
            stack.ventricleIds.push_back(id.get<std::int32_t>());
        }
    }
    if (j.contains("source") && !j["source"].is_object())
        return rd.bad("source", "expected an object");
    stack.source = j.value("source", json::object());
    return stack;
}

/// Writes `plane` (when not empty) as `dir`/`prefix`-NNN.tif after checking its type and size.
/// \return its file name, "" for an empty plane; InvalidArgument naming the slice, or the file
///         layer's error.
core::Result<std::string> writeBesidePlane(const fs::path& dir, const char* prefix, size_t index,
                                           const cv::Mat& plane, int type, cv::Size size,
                                           const char* typeName) {
    if (plane.empty())
        return std::string();
    if (plane.type() != type || plane.size() != size)
        return makeError(ErrorCode::InvalidArgument, "slice " + std::to_string(index) + ": the " +
                                                         prefix + " plane must be " + typeName +
                                                         " of the slice's size");
    char name[48];
    std::snprintf(name, sizeof name, "%s-%03zu.tif", prefix, index);
    if (auto w = core::writeImage(dir / name, plane); !w)
        return w.error();
    return std::string(name);
}

} // namespace

std::string colorHex(std::uint32_t rgb) {
    char buf[8];
    std::snprintf(buf, sizeof buf, "#%06X", rgb & 0xFFFFFFu);
    return buf;
}

const StackRegion* findRegion(const AtlasStack& stack, std::uint32_t id) noexcept {
    if (id == 0)
        return nullptr;
    const auto it = std::find_if(stack.regions.begin(), stack.regions.end(),
                                 [id](const StackRegion& r) { return r.id == id; });
    return it == stack.regions.end() ? nullptr : &*it;
}

core::Result<AtlasStack> writeStack(const fs::path& dir,
                                    const std::vector<pipeline::AtlasSlice>& slices,
                                    std::vector<StackRegion> regions, json source,
                                    std::vector<std::int32_t> ventricleIds) {
    if (slices.empty())
        return makeError(ErrorCode::InvalidArgument, "the stack has no slices");
    std::error_code ec;
    fs::create_directories(dir, ec);
    if (ec)
        return makeError(ErrorCode::IoError, "cannot create " + dir.string(), ec.value());
    AtlasStack stack;
    stack.dir = dir;
    json js = json::array();
    for (size_t i = 0; i < slices.size(); ++i) {
        char name[32];
        std::snprintf(name, sizeof name, "slice-%03zu.tif", i);
        if (auto w = core::writeImage(dir / name, slices[i].labels); !w)
            return w.error();
        const pipeline::SliceGeometry& g = slices[i].geometry;
        StackSlice s{int(i), name, g.positionUm, cv::norm(g.columnUm), g};
        // The optional planes beside the labels: the intensity (template) and every id.
        auto template_ = writeBesidePlane(dir, "template", i, slices[i].intensity, CV_32F,
                                          slices[i].labels.size(), "float32");
        if (!template_)
            return template_.error();
        s.templateFile = *template_;
        auto ids = writeBesidePlane(dir, "ids", i, slices[i].ids, CV_32S, slices[i].labels.size(),
                                    "32-bit ids");
        if (!ids)
            return ids.error();
        s.idsFile = *ids;
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
        if (!s.templateFile.empty())
            js.back()["template"] = s.templateFile;
        if (!s.idsFile.empty())
            js.back()["ids"] = s.idsFile;
        stack.slices.push_back(std::move(s));
    }
    json jr = json::array();
    for (const StackRegion& r : regions) {
        json e{{"id", r.id},
               {"name", r.name},
               {"acronym", r.acronym},
               {"color", colorHex(r.colorRgb)}};
        if (!r.path.empty())
            e["path"] = r.path;
        jr.push_back(std::move(e));
    }
    source["frame"] = "micrometres along (AP, DV, LR) from the centre of the first voxel";
    json manifest = {{"slices", js}, {"regions", jr}, {"source", source}};
    if (!ventricleIds.empty())
        manifest["ventricle_ids"] = ventricleIds;
    if (auto w = core::writeFileAtomically(dir / "manifest.json", manifest.dump(2) + "\n"); !w)
        return w.error();
    stack.regions = std::move(regions);
    stack.source = std::move(source);
    stack.ventricleIds = std::move(ventricleIds);
    return stack;
}

core::Result<AtlasStack> readStack(const fs::path& dirOrManifest) {
    std::error_code ec;
    const bool isFile = dirOrManifest.filename() == "manifest.json" ||
                        (fs::exists(dirOrManifest, ec) && !fs::is_directory(dirOrManifest, ec));
    const fs::path manifest = isFile ? dirOrManifest : dirOrManifest / "manifest.json";
    if (!fs::exists(manifest, ec))
        return makeError(ErrorCode::NotFound, "no atlas stack manifest at " + manifest.string());
    const std::uintmax_t bytes = fs::file_size(manifest, ec);
    if (!ec && bytes > kMaxManifestBytes)
        return makeError(ErrorCode::InvalidArgument,
                         manifest.string() + ": " + std::to_string(bytes) +
                             " bytes, more than a manifest may hold (" +
                             std::to_string(kMaxManifestBytes >> 20) + " MiB)");
    std::ifstream in(manifest, std::ios::binary);
    if (!in)
        return makeError(ErrorCode::IoError, "cannot read " + manifest.string(), errno);
    std::ostringstream text;
    text << in.rdbuf();
    if (in.bad())
        return makeError(ErrorCode::IoError, "cannot read " + manifest.string(), errno);
    // The one place nlohmann is called on the manifest: no exception gets past it.
    try {
        auto j = parseDocument(text.str(), DocumentFormat::Json, manifest.string());
        if (!j)
            return j.error();
        return stackFromJson(*j, manifest);
    } catch (const json::exception& e) {
        return makeError(ErrorCode::InvalidArgument, manifest.string() + ": " + e.what());
    } catch (const std::exception& e) {
        return makeError(ErrorCode::Internal, manifest.string() + ": " + e.what());
    }
}

core::Result<fs::path> stackSlicePath(const AtlasStack& stack, int index) {
    if (index < 0 || index >= int(stack.slices.size()))
        return makeError(ErrorCode::OutOfRange,
                         "slice " + std::to_string(index) + " is not in the stack at " +
                             stack.dir.string() + " (0.." +
                             std::to_string(int(stack.slices.size()) - 1) + ")");
    return stack.dir / stack.slices[size_t(index)].file;
}

core::Result<cv::Mat> readStackTemplate(const AtlasStack& stack, int index) {
    if (index < 0 || index >= int(stack.slices.size()))
        return makeError(ErrorCode::OutOfRange, "slice " + std::to_string(index) +
                                                    " is not in the stack at " +
                                                    stack.dir.string());
    const StackSlice& s = stack.slices[size_t(index)];
    if (s.templateFile.empty())
        return cv::Mat();
    return readTemplatePlane(stack.dir, index, s.templateFile, s.geometry.size);
}

core::Result<cv::Mat> readTemplatePlane(const fs::path& dir, int index, const std::string& file,
                                        cv::Size size) {
    const fs::path path = dir / file;
    const std::string entry = (dir / "manifest.json").string() + ": slices[" +
                              std::to_string(index) + "].template (" + path.string() + ")";
    auto image = core::readImage(path);
    if (!image)
        return makeError(image.error().code, entry + ": " + image.error().message,
                         image.error().sysErrno);
    if (image->type() != CV_32F)
        return makeError(ErrorCode::InvalidArgument,
                         entry + ": expected a one-channel float32 image");
    if (size.area() > 0 && image->size() != size)
        return makeError(ErrorCode::InvalidArgument,
                         entry + ": " + std::to_string(image->cols) + " x " +
                             std::to_string(image->rows) + " px, the slice is " +
                             std::to_string(size.width) + " x " + std::to_string(size.height));
    return image;
}

core::Result<cv::Mat> readStackSlice(const AtlasStack& stack, int index) {
    auto path = stackSlicePath(stack, index);
    if (!path)
        return path.error();
    auto image = core::readImage(*path);
    if (!image)
        return image.error();
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
        return makeError(ErrorCode::OutOfRange, "first_um " + std::to_string(firstUm) +
                                                    " is outside the built-in brain (0.." +
                                                    std::to_string(int(kBuiltinLengthUm)) + " um)");
    // Known before a plane is drawn: every built-in plane has the size of the first.
    const double planes = 1 + std::floor((kBuiltinLengthUm + 1e-6 - firstUm) / intervalUm);
    if (auto budget = pipeline::checkStackBudget(
            planes, sim::builtinAtlasPlane(firstUm / kBuiltinLengthUm).size());
        !budget)
        return budget.error();
    std::vector<pipeline::AtlasSlice> slices;
    for (int i = 0;; ++i) {
        const double pos = firstUm + i * intervalUm;
        if (pos > kBuiltinLengthUm + 1e-6)
            break;
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

core::Result<std::vector<pipeline::SliceFeatures>> stackFeatures(const AtlasStack& stack) {
    std::vector<cv::Mat> labels;
    for (const StackSlice& s : stack.slices) {
        auto l = readStackSlice(stack, s.index);
        if (!l)
            return l.error();
        labels.push_back(std::move(*l));
    }
    // One working pixel size for the whole stack, from its largest brain and finest slices.
    double umPerPx = stack.slices.front().umPerPx;
    for (const StackSlice& s : stack.slices)
        umPerPx = std::min(umPerPx, s.umPerPx);
    const double workUm = pipeline::matchWorkUmPerPx(labels, umPerPx);
    std::vector<pipeline::SliceFeatures> features;
    for (size_t i = 0; i < labels.size(); ++i)
        features.push_back(pipeline::sliceFeatures(labels[i], stack.slices[i].umPerPx,
                                                   stack.slices[i].positionUm, workUm));
    return features;
}

} // namespace slicestation::daemon
