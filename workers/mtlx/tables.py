"""The constant tables of the GLSL PPTBF (library/genglsl/lib/pptbf_tables.glsl), generated from pptbf_db.

`glsl_tables()` builds the file's text; ``python -m workers.mtlx.tables`` rewrites the file. Everything tabular
that pptbf_core.glsl needs comes from here: the hash permutation and value-noise table, the powers of the PRNG
multiplier (random access to the n-th draw), the 18 tiling types, and for the table-driven families (CROSS N=2 and
N=3, BISQUARE, APAVEMENT) the tiles of pptbf._TABLES in two forms:

* per sub-cell code q and slot (q * 9 + slot): the tile's integer cell offset from the code's cell and its index
  in the family's list of *owned* tiles (the distinct tiles with their centre in one period cell, as fractions in
  [0, 1)). The candidates of a pixel are the 9 tiles of its code; the cell-border neighbourhood enumerates the
  owned tiles of the cells around p0's, each tile once.
* per owned tile: centre fraction and half sizes (float32), and for a coordinate whose fraction is not a dyadic
  number (k/5, k/10, k/12) an index into the exact-centre table. numpy hashes floor(m * cx) of float64 tile
  centres; where m * cx is an integer in exact arithmetic (15 * (ix + 1/5)) the float64 rounding of cx decides the
  seed. That rounding depends only on the fraction, the sign and the binade of cx: the table gives its residual in
  ulps (measured here on float64 arithmetic), from which pptbf_xfloor in pptbf_core.glsl derives numpy's floor.
  The PAVE thirds-bond rows (a + 1/3 + 1/2, numpy's two float64 additions) are entries of the same table.

Floats are written as the shortest decimal of the float64 value of the float32 (repr(float(np.float32(v)))):
parsed to float32 directly or through float64 both give exactly np.float32(v).
"""
from __future__ import annotations

import math
from fractions import Fraction
from pathlib import Path

import numpy as np

from pptbf_db import pptbf as pp
from pptbf_db import tables as ptab

OUT_PATH = Path(__file__).resolve().parent / "library" / "genglsl" / "lib" / "pptbf_tables.glsl"

#: family ids of the GLSL: 0 = PAVE, then the table-driven families in this order
TABLE_FAMILIES = (("cross", 2), ("cross", 3), ("bisquare", 0), ("apave", 0))

#: the fraction denominators the tile tables use (the exact rationals are recovered with this bound)
_MAX_DEN = 240


def f32(v: float) -> str:
    """GLSL literal of np.float32(v): the float64 repr of the float32 value (exact under either parse)."""
    x = float(np.float32(v))
    if not math.isfinite(x):
        raise ValueError(f"non-finite table value {v}")
    s = repr(x)
    if "e" not in s and "." not in s:
        s += ".0"
    return s


def _array(kind: str, name: str, items: list[str], per_line: int = 8) -> str:
    """A GLSL const array declaration."""
    lines = []
    for i in range(0, len(items), per_line):
        lines.append("    " + ", ".join(items[i:i + per_line]))
    body = ",\n".join(lines)
    return f"const {kind} {name}[{len(items)}] = {kind}[{len(items)}](\n{body});\n"


#: binades of |centre| covered by the residual table (centres of up to 2^28 cells)
RHO_BINADES = 32


def _binade(x: Fraction) -> int:
    """floor(log2 |x|) of a non-zero exact rational."""
    x = abs(x)
    e = x.numerator.bit_length() - x.denominator.bit_length()
    if Fraction(2) ** e > x:
        e -= 1
    return e


def numpy_centre(cell: int, frac: Fraction, plus_half: bool) -> float:
    """numpy's float64 tile centre: cell + fl64(frac) (tile tables), or (a + fl64(o)) + 0.5 (PAVE thirds rows)."""
    c = float(cell) + float(frac)
    return c + 0.5 if plus_half else c


def _rho_rows(frac: Fraction, plus_half: bool) -> list[float]:
    """Residual of numpy's float64 centre: rho = (|c64| - |c|) / ulp(|c|) for the exact centre c = cell + frac
    (+ 1/2), as a function of (sign of c, binade E of |c|, cross). cross = 1 where the float64 sum (a + o) lies in
    another binade than c (the thirds rows only): the rounding of the + 0.5 step then matters. Each key is
    measured on representative cells and asserted to give one residual (it depends on the fraction's bits at the
    ulp, not on the cell). Layout: [neg][E][cross], RHO_BINADES binades from E = 0."""
    val = frac + (Fraction(1, 2) if plus_half else 0)
    rows = [0.0] * (2 * RHO_BINADES * 2)
    seen: dict[tuple, Fraction] = {}
    cells = list(range(-300, 301))
    cells += [s * (2 ** k + d) for k in range(9, RHO_BINADES) for d in range(-3, 4) for s in (1, -1)]
    for cell in cells:
        c = cell + val
        if c == 0 or abs(c) < 1:
            continue
        e = _binade(c)
        if e >= RHO_BINADES:
            continue
        cross = int(_binade(cell + frac) != e) if plus_half and cell + frac != 0 else 0
        rho = (abs(Fraction(numpy_centre(cell, frac, plus_half))) - abs(c)) / Fraction(2) ** (e - 52)
        key = (int(c < 0), e, cross)
        if seen.setdefault(key, rho) != rho:
            raise AssertionError(f"residual of {frac} (+1/2: {plus_half}) not unique for {key}")
        rows[(key[0] * RHO_BINADES + e) * 2 + cross] = float(rho)
    return rows


class _Exact:
    """The exact-centre table: per entry its rational position relative to the cell (num / den), whether numpy
    adds 0.5 after the float64 sum (PAVE thirds rows), and the float64 residual rows (_rho_rows)."""

    def __init__(self) -> None:
        self.rows: list[tuple[int, int, int]] = []
        self.rho: list[float] = []
        self.index: dict[tuple[Fraction, int], int] = {}

    def get(self, frac: Fraction, plus_half: bool = False) -> int:
        """Index of (frac, plus_half), -1 for a dyadic fraction without the +0.5 step (float32 is exact there)."""
        if not plus_half and (frac.denominator & (frac.denominator - 1)) == 0:
            return -1
        key = (frac, int(plus_half))
        if key not in self.index:
            val = frac + (Fraction(1, 2) if plus_half else 0)
            self.index[key] = len(self.rows)
            self.rows.append((val.numerator, val.denominator, int(plus_half)))
            self.rho += _rho_rows(frac, plus_half)
        return self.index[key]


def _table_family(tab: np.ndarray, n: int, exact: _Exact, own_base: int):
    """(code rows (dcx, dcy, owned index), owned rows (fx, fy, hx, hy, ex_x, ex_y)) of one tile table."""
    owned: dict[tuple, int] = {}
    own_rows: list[tuple] = []
    codes: list[tuple[int, int, int]] = []
    for q in range(n * n):
        for s in range(9):
            cx, cy, hx, hy = (Fraction(float(v)).limit_denominator(_MAX_DEN) for v in tab[q, s])
            dcx, dcy = math.floor(cx), math.floor(cy)
            key = (cx - dcx, cy - dcy, hx, hy)
            if key not in owned:
                owned[key] = len(own_rows)
                fx, fy = key[0], key[1]
                own_rows.append((fx, fy, hx, hy, exact.get(fx), exact.get(fy)))
            codes.append((dcx, dcy, own_base + owned[key]))
    return codes, own_rows


def _family_tables(exact: _Exact):
    """The table families' code rows and owned tiles, concatenated, and per family: sub-units per period, first
    code row, first owned tile, owned tiles per cell."""
    codes_all: list[tuple[int, int, int]] = []
    own_all: list[tuple] = []
    fam_n, fam_code0, fam_own0, fam_nown = [], [], [], []
    for key in TABLE_FAMILIES:
        n, tab = pp._TABLES[key]
        codes, own = _table_family(tab, n, exact, len(own_all))
        fam_n.append(n)
        fam_code0.append(len(codes_all))
        fam_own0.append(len(own_all))
        fam_nown.append(len(own))
        codes_all += codes
        own_all += own
    return codes_all, own_all, fam_n, fam_code0, fam_own0, fam_nown


def glsl_tables() -> str:
    """The text of pptbf_tables.glsl."""
    out = ["// GENERATED by `python -m workers.mtlx.tables` from pptbf_db (tables.py, pptbf.py): do not edit.\n"
           "// Constant tables of the GLSL PPTBF (pptbf_core.glsl); see workers/mtlx/tables.py.\n"]
    out.append(_array("int", "pptbf_perm", [str(int(v)) for v in ptab.PERM], 16))
    out.append(_array("float", "pptbf_noise", [f32(v) for v in ptab.NOISE], 6))
    out.append("// M^n mod 2^32 for the n-th draw after seeding (n = 0..MAX_DRAWS)\n")
    out.append(_array("uint", "pptbf_mpow", [f"{int(v)}u" for v in pp.MPOW], 8))

    exact = _Exact()
    # PAVE row offsets o = (b mod shift) / shift: numpy computes a + o (float64) then + 0.5 (hx)
    third = [-1] + [exact.get(Fraction(k, 3), plus_half=True) for k in (1, 2)]

    fam_of = {key: i + 1 for i, key in enumerate(TABLE_FAMILIES)}
    tt = pp.TILING_TYPES
    out.append("// tiling types 0..17: family (0 PAVE, 1 CROSS N=2, 2 CROSS N=3, 3 BISQUARE, 4 APAVEMENT), "
               "subdivision\n// probability, PAVE random cut amplitudes and row shift, relaxation iterations\n")
    out.append(_array("int", "pptbf_tt_family",
                      [str(0 if t.family == "pave" else fam_of[(t.family, t.n)]) for t in tt], 18))
    out.append(_array("float", "pptbf_tt_psub", [f32(t.p_sub) for t in tt], 9))
    out.append(_array("float", "pptbf_tt_randx", [f32(t.rand_x) for t in tt], 9))
    out.append(_array("float", "pptbf_tt_randy", [f32(t.rand_y) for t in tt], 9))
    out.append(_array("int", "pptbf_tt_shift", [str(t.shift) for t in tt], 18))
    out.append(_array("int", "pptbf_tt_relax", [str(t.relax) for t in tt], 18))
    out.append(_array("int", "pptbf_third_ex", [str(v) for v in third], 3))

    codes_all, own_all, fam_n, fam_code0, fam_own0, fam_nown = _family_tables(exact)
    out.append("// table families 1..4 (index family - 1): sub-units per period, first code row, first owned tile,\n"
               "// owned tiles per cell\n")
    out.append(_array("int", "pptbf_fam_n", [str(v) for v in fam_n], 4))
    out.append(_array("int", "pptbf_fam_code0", [str(v) for v in fam_code0], 4))
    out.append(_array("int", "pptbf_fam_own0", [str(v) for v in fam_own0], 4))
    out.append(_array("int", "pptbf_fam_nown", [str(v) for v in fam_nown], 4))
    out.append(f"const int pptbf_max_own = {max(fam_nown)};\n")
    out.append("// per code row (q * 9 + slot, q = qx * n + qy): the tile's cell offset and its owned-tile index\n")
    out.append(_array("ivec3", "pptbf_code", [f"ivec3({a}, {b}, {c})" for a, b, c in codes_all], 6))
    out.append("// owned tiles: centre fraction in [0, 1) within the cell and half sizes\n")
    out.append(_array("vec4", "pptbf_own",
                      [f"vec4({f32(r[0])}, {f32(r[1])}, {f32(r[2])}, {f32(r[3])})" for r in own_all], 2))
    out.append("// owned tiles: exact-fraction index of the centre's x and y (-1: dyadic, float32 is exact)\n")
    out.append(_array("ivec2", "pptbf_own_ex", [f"ivec2({r[4]}, {r[5]})" for r in own_all], 8))
    out.append("// exact centres: the position relative to the cell num / den, whether numpy adds 0.5 to the "
               "float64\n// sum (PAVE thirds rows); residuals of numpy's float64 centre in ulps, per entry "
               "[neg][binade][cross]\n")
    out.append(_array("ivec3", "pptbf_ex_rat", [f"ivec3({r[0]}, {r[1]}, {r[2]})" for r in exact.rows], 6))
    out.append(f"const int pptbf_rho_binades = {RHO_BINADES};\n")
    out.append(_array("float", "pptbf_ex_rho", [f32(v) for v in exact.rho], 8))
    return "\n".join(out)



OSL_OUT_PATH = Path(__file__).resolve().parent / "library" / "genosl" / "lib" / "pptbf_tables.osl"


def _osl_i32(v: int) -> str:
    """OSL literal of a uint32 held in OSL's 32-bit int: hex from 2^31 on (OSL reads 0x80000000.. as the
    wrapped negative int, which is the bit pattern the GLSL's uint has)."""
    v = int(v)
    if not 0 <= v < 2 ** 32:
        raise ValueError(f"not a uint32: {v}")
    return str(v) if v < 2 ** 31 else f"0x{v:08x}"


def _osl_lookup(kind: str, name: str, items: list[str], doc: str, per_line: int = 8) -> str:
    """An OSL lookup function ``kind name(int i)`` over a constant table. OSL has no global variables: the table
    is a local array with a constant initialiser (oslc stores it once as a constant, the runtime optimiser reads
    it in place)."""
    lines = []
    for i in range(0, len(items), per_line):
        lines.append("        " + ", ".join(items[i:i + per_line]))
    body = ",\n".join(lines)
    return (f"// {doc}\n{kind} {name}(int i)\n{{\n    {kind} t[{len(items)}] = {{\n{body}}};\n"
            f"    return t[i];\n}}\n")


def osl_tables() -> str:
    """The text of genosl/lib/pptbf_tables.osl: the tables of :func:`glsl_tables` as OSL lookup functions (same
    names; ``pptbf_perm(i)`` for the GLSL's ``pptbf_perm[i]``). Vector rows are flattened: ``pptbf_code(3 * row
    + c)``, ``pptbf_own(4 * row + c)``, ``pptbf_own_ex(2 * row + c)``, ``pptbf_ex_rat(3 * row + c)``; the uint
    multiplier powers are their bit patterns in int (OSL has no unsigned type)."""
    out = ["// GENERATED by `python -m workers.mtlx.osl` from pptbf_db (tables.py, pptbf.py): do not edit.\n"
           "// Constant tables of the OSL PPTBF (pptbf_core.osl), the same as genglsl/lib/pptbf_tables.glsl;\n"
           "// see workers/mtlx/tables.py.\n#ifndef PPTBF_TABLES_OSL\n#define PPTBF_TABLES_OSL\n"]
    out.append(_osl_lookup("int", "pptbf_perm", [str(int(v)) for v in ptab.PERM], "hash permutation", 16))
    out.append(_osl_lookup("float", "pptbf_noise", [f32(v) for v in ptab.NOISE], "value-noise lattice", 6))
    out.append(_osl_lookup("int", "pptbf_mpow", [_osl_i32(v) for v in pp.MPOW],
                           "M^n mod 2^32 for the n-th draw after seeding (n = 0..MAX_DRAWS), as int bits", 8))

    exact = _Exact()
    third = [-1] + [exact.get(Fraction(k, 3), plus_half=True) for k in (1, 2)]
    fam_of = {key: i + 1 for i, key in enumerate(TABLE_FAMILIES)}
    tt = pp.TILING_TYPES
    out.append(_osl_lookup("int", "pptbf_tt_family",
                           [str(0 if t.family == "pave" else fam_of[(t.family, t.n)]) for t in tt],
                           "tiling types 0..17: family (0 PAVE, 1 CROSS N=2, 2 CROSS N=3, 3 BISQUARE, 4 APAVEMENT)",
                           18))
    out.append(_osl_lookup("float", "pptbf_tt_psub", [f32(t.p_sub) for t in tt], "subdivision probability", 9))
    out.append(_osl_lookup("float", "pptbf_tt_randx", [f32(t.rand_x) for t in tt], "PAVE random cuts in x", 9))
    out.append(_osl_lookup("float", "pptbf_tt_randy", [f32(t.rand_y) for t in tt], "PAVE random cuts in y", 9))
    out.append(_osl_lookup("int", "pptbf_tt_shift", [str(t.shift) for t in tt], "PAVE row shift", 18))
    out.append(_osl_lookup("int", "pptbf_tt_relax", [str(t.relax) for t in tt], "relaxation iterations", 18))
    out.append(_osl_lookup("int", "pptbf_third_ex", [str(v) for v in third], "PAVE row offsets: exact entries", 3))

    codes_all, own_all, fam_n, fam_code0, fam_own0, fam_nown = _family_tables(exact)
    fam = "table families 1..4 (index family - 1): "
    out.append(_osl_lookup("int", "pptbf_fam_n", [str(v) for v in fam_n], fam + "sub-units per period", 4))
    out.append(_osl_lookup("int", "pptbf_fam_code0", [str(v) for v in fam_code0], fam + "first code row", 4))
    out.append(_osl_lookup("int", "pptbf_fam_own0", [str(v) for v in fam_own0], fam + "first owned tile", 4))
    out.append(_osl_lookup("int", "pptbf_fam_nown", [str(v) for v in fam_nown], fam + "owned tiles per cell", 4))
    out.append(f"#define pptbf_max_own {max(fam_nown)}\n")
    out.append(_osl_lookup("int", "pptbf_code", [str(v) for row in codes_all for v in row],
                           "per code row r (q * 9 + slot, q = qx * n + qy), at 3 r + (0, 1, 2): the tile's cell "
                           "offset and its owned-tile index", 18))
    out.append(_osl_lookup("float", "pptbf_own", [f32(v) for r in own_all for v in r[:4]],
                           "owned tiles, at 4 r + (0..3): centre fraction in [0, 1) within the cell, half sizes", 4))
    out.append(_osl_lookup("int", "pptbf_own_ex", [str(v) for r in own_all for v in r[4:6]],
                           "owned tiles, at 2 r + (0, 1): exact-fraction index of the centre's x, y (-1: dyadic)",
                           16))
    out.append(_osl_lookup("int", "pptbf_ex_rat", [str(v) for r in exact.rows for v in r],
                           "exact centres, at 3 r + (0, 1, 2): num, den of the position in the cell, whether numpy "
                           "adds 0.5 to the float64 sum", 18))
    out.append(f"#define pptbf_rho_binades {RHO_BINADES}\n")
    out.append(_osl_lookup("float", "pptbf_ex_rho", [f32(v) for v in exact.rho],
                           "residuals of numpy's float64 centre in ulps, per entry [neg][binade][cross]", 8))
    out.append("#endif\n")
    return "\n".join(out)

def main(argv=None) -> None:
    """Rewrite library/genglsl/lib/pptbf_tables.glsl."""
    text = glsl_tables()
    OUT_PATH.parent.mkdir(parents=True, exist_ok=True)
    OUT_PATH.write_text(text, encoding="utf-8")
    print(f"wrote {OUT_PATH} ({len(text)} chars)")


if __name__ == "__main__":
    main()
