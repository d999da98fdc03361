#include "slicestation/core/ontology.hpp"

#include "slicestation/core/csv.hpp"

#include <algorithm>
#include <cerrno>
#include <charconv>
#include <cstring>
#include <fstream>
#include <limits>
#include <new>
#include <optional>
#include <sstream>
#include <unordered_set>

namespace slicestation::core {

Result<Ontology> Ontology::create(std::vector<Structure> structures) {
    Ontology ontology;
    ontology.indexById_.reserve(structures.size());
    for (std::size_t i = 0; i < structures.size(); ++i) {
        const Structure& s = structures[i];
        const std::string which = "structure " + std::to_string(s.id) + " ('" + s.name + "')";
        if (s.id == 0) {
            return makeError(ErrorCode::InvalidArgument,
                             "ontology: structure #" + std::to_string(i) + " has id 0");
        }
        if (s.path.empty() || s.path.back() != s.id) {
            return makeError(ErrorCode::InvalidArgument,
                             "ontology: path of " + which + " does not end with its id");
        }
        if (!ontology.indexById_.emplace(s.id, i).second) {
            return makeError(ErrorCode::InvalidArgument, "ontology: duplicate id in " + which);
        }
    }
    ontology.structures_ = std::move(structures);
    return ontology;
}

const Structure* Ontology::find(std::uint32_t id) const {
    const auto it = indexById_.find(id);
    return it == indexById_.end() ? nullptr : &structures_[it->second];
}

bool Ontology::isDescendantOf(std::uint32_t id, std::uint32_t ancestorId) const {
    const Structure* s = find(id);
    return s != nullptr && std::find(s->path.begin(), s->path.end(), ancestorId) != s->path.end();
}

namespace {

/// The Allen structure tree is 224 KB; 64 MiB leaves room for any ontology and keeps a wrong
/// file (a volume given as --ontology) from being read whole into memory.
constexpr std::uintmax_t kMaxOntologyBytes = std::uintmax_t{64} << 20;

std::optional<std::uint32_t> parseId(std::string_view text) {
    std::uint64_t value = 0;
    const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
    if (text.empty() || ec != std::errc() || end != text.data() + text.size() ||
        value > std::numeric_limits<std::uint32_t>::max()) {
        return std::nullopt;
    }
    return static_cast<std::uint32_t>(value);
}

class OntologyCsvReader {
public:
    explicit OntologyCsvReader(std::filesystem::path path)
        : path_(std::move(path)), where_("ontology CSV '" + path_.string() + "'") {}

    Result<Ontology> read() {
        auto text = readFile();
        if (!text) {
            return text.error();
        }
        auto records = parseCsv(*text, where_);
        if (!records) {
            return records.error();
        }
        if (records->empty()) {
            return makeError(ErrorCode::InvalidArgument, where_ + " has no header row");
        }
        if (auto columns = findColumns(records->front()); !columns) {
            return columns.error();
        }
        std::vector<Structure> structures;
        structures.reserve(records->size() - 1);
        std::unordered_map<std::uint32_t, int> lineById;
        for (std::size_t r = 1; r < records->size(); ++r) {
            const CsvRecord& record = (*records)[r];
            auto structure = toStructure(record);
            if (!structure) {
                return structure.error();
            }
            const auto [it, inserted] = lineById.emplace(structure->id, record.line);
            if (!inserted) {
                return makeError(ErrorCode::InvalidArgument,
                                 at(record.line, "id") + ": id " + std::to_string(structure->id) +
                                     " already given on line " + std::to_string(it->second));
            }
            structures.push_back(std::move(structure.value()));
        }
        return Ontology::create(std::move(structures));
    }

private:
    struct Columns {
        std::size_t id = 0, name = 0, acronym = 0, parent = 0, path = 0, color = 0;
        std::size_t count = 0;
    };

    std::string at(int line, const char* column) const {
        return where_ + ": line " + std::to_string(line) + ", column '" + column + "'";
    }

    Result<std::string> readFile() const {
        std::error_code ec;
        const auto status = std::filesystem::status(path_, ec);
        if (!std::filesystem::exists(status)) {
            return makeError(ErrorCode::NotFound, where_ + " does not exist");
        }
        std::ifstream in(path_, std::ios::binary);
        if (!in.is_open() || std::filesystem::is_directory(status)) {
            const int err = errno;
            return makeError(ErrorCode::IoError, "cannot open " + where_, err);
        }
        const std::uintmax_t fileBytes = std::filesystem::file_size(path_, ec);
        if (!ec && fileBytes > kMaxOntologyBytes) {
            return makeError(
                ErrorCode::InvalidArgument,
                where_ + " has " + std::to_string(fileBytes) + " bytes, more than the " +
                    std::to_string(kMaxOntologyBytes >> 20) + " MiB an ontology may hold");
        }
        std::ostringstream bytes;
        bytes << in.rdbuf();
        return std::move(bytes).str(); // parseCsv skips a byte-order mark
    }

    Result<void> findColumns(const CsvRecord& header) {
        const auto column = [&](const char* name, std::size_t& index) -> Result<void> {
            const auto it = std::find(header.fields.begin(), header.fields.end(), name);
            if (it == header.fields.end()) {
                return makeError(ErrorCode::InvalidArgument,
                                 where_ + ": line " + std::to_string(header.line) +
                                     ": header lacks column '" + name + "'");
            }
            index = static_cast<std::size_t>(it - header.fields.begin());
            return {};
        };
        for (const auto& [name, index] : {std::pair<const char*, std::size_t*>{"id", &columns_.id},
                                          {"name", &columns_.name},
                                          {"acronym", &columns_.acronym},
                                          {"parent_structure_id", &columns_.parent},
                                          {"structure_id_path", &columns_.path},
                                          {"color_hex_triplet", &columns_.color}}) {
            if (auto found = column(name, *index); !found) {
                return found;
            }
        }
        columns_.count = header.fields.size();
        return {};
    }

    Result<Structure> toStructure(const CsvRecord& record) const {
        if (record.fields.size() != columns_.count) {
            return makeError(ErrorCode::InvalidArgument,
                             where_ + ": line " + std::to_string(record.line) + ": expected " +
                                 std::to_string(columns_.count) + " fields like the header, got " +
                                 std::to_string(record.fields.size()));
        }
        const auto& f = record.fields;
        Structure s;
        const auto id = parseId(f[columns_.id]);
        if (!id || *id == 0) {
            return makeError(ErrorCode::InvalidArgument, at(record.line, "id") + ": '" +
                                                             f[columns_.id] +
                                                             "' is not a positive 32-bit id");
        }
        s.id = *id;
        s.name = f[columns_.name];
        s.acronym = f[columns_.acronym];
        if (!f[columns_.parent].empty()) {
            const auto parent = parseId(f[columns_.parent]);
            if (!parent) {
                return makeError(ErrorCode::InvalidArgument,
                                 at(record.line, "parent_structure_id") + ": '" +
                                     f[columns_.parent] + "' is not an id");
            }
            s.parentId = *parent;
        }

        const std::string& pathText = f[columns_.path];
        std::string_view rest(pathText);
        while (!rest.empty()) {
            const std::size_t slash = rest.find('/');
            const std::string_view part = rest.substr(0, slash);
            rest = slash == std::string_view::npos ? std::string_view() : rest.substr(slash + 1);
            if (part.empty()) {
                continue;
            }
            const auto step = parseId(part);
            if (!step) {
                return makeError(ErrorCode::InvalidArgument,
                                 at(record.line, "structure_id_path") + ": '" + pathText +
                                     "' holds '" + std::string(part) + "', not an id");
            }
            s.path.push_back(*step);
        }
        if (s.path.empty() || s.path.back() != s.id) {
            return makeError(ErrorCode::InvalidArgument,
                             at(record.line, "structure_id_path") + ": '" + pathText +
                                 "' does not end with the structure's id " + std::to_string(s.id));
        }
        const std::uint32_t pathParent = s.path.size() >= 2 ? s.path[s.path.size() - 2] : 0;
        if (pathParent != s.parentId) {
            return makeError(ErrorCode::InvalidArgument, at(record.line, "parent_structure_id") +
                                                             ": " + std::to_string(s.parentId) +
                                                             " does not match the path '" +
                                                             pathText + "'");
        }

        std::string_view color(f[columns_.color]);
        if (!color.empty() && color.front() == '#') {
            color.remove_prefix(1);
        }
        std::uint32_t rgb = 0;
        const auto [end, ec] = std::from_chars(color.data(), color.data() + color.size(), rgb, 16);
        if (color.size() != 6 || ec != std::errc() || end != color.data() + color.size()) {
            return makeError(ErrorCode::InvalidArgument, at(record.line, "color_hex_triplet") +
                                                             ": '" + f[columns_.color] +
                                                             "' is not 6 hex digits");
        }
        s.colorRgb = rgb;
        return s;
    }

    std::filesystem::path path_;
    std::string where_;
    Columns columns_;
};

} // namespace

Result<Ontology> readOntologyCsv(const std::filesystem::path& path) {
    try {
        return OntologyCsvReader(path).read();
    } catch (const std::bad_alloc&) {
        return makeError(ErrorCode::IoError,
                         "ontology CSV '" + path.string() + "' is too large to load");
    } catch (const std::exception& e) {
        return makeError(ErrorCode::Internal, "ontology CSV '" + path.string() + "': " + e.what());
    }
}

Result<Ontology> readOntologyCsvIfGiven(const std::filesystem::path& path) {
    if (path.empty())
        return Ontology{};
    return readOntologyCsv(path);
}

} // namespace slicestation::core
