#pragma once
/// The one CSV reader (RFC 4180): the ontology (core/ontology) and the points of
/// `slicectl register --points` read their files through it.
///
/// Fields are separated by commas; a field in double quotes may hold commas, doubled quotes ("")
/// and line breaks; a quote inside an unquoted field, or anything but a comma or a line end after
/// a closing quote, is an error. Lines end in LF or CRLF. A leading UTF-8 byte-order mark (what
/// spreadsheets write) is skipped. Blank lines are skipped. Fields are not trimmed: a caller that
/// allows spaces around numbers trims them. Pure, re-entrant, no I/O.
#include "slicestation/core/result.hpp"

#include <string>
#include <string_view>
#include <vector>

namespace slicestation::core {

struct CsvRecord {
    int line = 0; ///< physical line on which the record starts, 1-based (the BOM is on line 1)
    std::vector<std::string> fields;
};

/// The records of `text`, in order. \return InvalidArgument for broken quoting, with the
/// message "<where>: line L, field F: what is wrong" (L the physical line, F 1-based).
[[nodiscard]] Result<std::vector<CsvRecord>> parseCsv(std::string_view text,
                                                      const std::string& where);

} // namespace slicestation::core
