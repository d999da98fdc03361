#pragma once
/// The Allen structure ontology: ids, names and the id -> ancestors tree.

#include "slicestation/core/result.hpp"

#include <cstdint>
#include <filesystem>
#include <string>
#include <unordered_map>
#include <vector>

namespace slicestation::core {

/// One brain structure of the Allen ontology.
struct Structure {
    std::uint32_t id = 0;
    std::uint32_t parentId = 0;      ///< 0 for the root
    std::string name;                ///< e.g. "Caudoputamen"
    std::string acronym;             ///< e.g. "CP"
    std::vector<std::uint32_t> path; ///< ancestors, root first, ends with `id`
    std::uint32_t colorRgb = 0;      ///< 0xRRGGBB
};

/// An immutable set of structures with lookup by id. Cheap to query; safe to share between
/// threads for reading.
class Ontology {
public:
    Ontology() = default; ///< empty: find() returns nullptr for every id

    /// Validates and indexes `structures`: ids unique and non-zero, every path non-empty and
    /// ending with its structure's id. InvalidArgument naming the offending id otherwise.
    [[nodiscard]] static Result<Ontology> create(std::vector<Structure> structures);

    /// The structure with this id, or nullptr if unknown. The pointer lives as long as *this.
    const Structure* find(std::uint32_t id) const;

    /// All structures in file order.
    const std::vector<Structure>& structures() const { return structures_; }

    /// True if `id` is `ancestorId` or lies below it in the tree (per the structure's path).
    /// False when `id` is unknown (including 0, "outside the brain").
    bool isDescendantOf(std::uint32_t id, std::uint32_t ancestorId) const;

private:
    std::vector<Structure> structures_;
    std::unordered_map<std::uint32_t, std::size_t> indexById_;
};

/// Reads the Allen `structure_tree_safe_2017.csv` format: a header row naming at least the
/// columns id, name, acronym, parent_structure_id, structure_id_path ("/997/8/567/") and
/// color_hex_triplet ("B0F0FF"), in any order; other columns are ignored. RFC 4180 quoting
/// (quoted fields may hold commas, doubled quotes and line breaks); LF or CRLF line ends; an
/// optional UTF-8 byte-order mark. An empty parent_structure_id marks the root (parentId 0).
/// Blocking file I/O; re-entrant.
///
/// At most 64 MiB (the Allen file is 224 KB).
///
/// \return the ontology; NotFound (no such file), IoError (unreadable), InvalidArgument (larger
///         than 64 MiB, empty
///         file, missing column, wrong field count, bad number, path or colour, duplicate id,
///         parent not matching the path, broken quoting): the message names the file, the line
///         number and the column.
[[nodiscard]] Result<Ontology> readOntologyCsv(const std::filesystem::path& path);

/// readOntologyCsv for an optional file: an empty path gives an empty ontology (no roll-up).
[[nodiscard]] Result<Ontology> readOntologyCsvIfGiven(const std::filesystem::path& path);

} // namespace slicestation::core
