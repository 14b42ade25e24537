// PPTBF (Point Process Texture Basis Functions, Guehl et al. 2020): pointwise GLSL evaluation of the raw value V.
//
// A port of our numpy generator pptbf_db/pptbf.py (with the exact cell borders of pptbf_db/border.py), re-derived
// from that code, in float32 (no double precision). Entry point:
//
//     float pptbf_eval(float x0, float y0, float ref_width, float prm[29], out float key);
//     float pptbf_eval_field(float x0, float y0, float ref_width, float prm[29], bool border, out float key);
//
// (and its parts pptbf_value, pptbf_cell).
// (x0, y0) = pixel / (ref_width * pixel_scale) + shift as pptbf.base_coords gives them, prm = the 29-vector in
// pptbf.PARAM_NAMES order, ref_width as in pptbf.evaluate (zoom = ref_width / int(resolution)). Tables (hash
// permutation, noise, multiplier powers, tile tables) are generated into pptbf_tables.glsl by workers/mtlx/tables.py.
//
// Organisation (numpy function in brackets):
//   hash / draws / value noise ........ pptbf_seed, pptbf_draw, pptbf_vnoise       (hash_seed, draw, value_noise)
//   float64 floors of tile centres ..... pptbf_x64_*, pptbf_hfloor*                 (the np.floor(m * cx) of hashes)
//   parameters, coordinates ............ pptbf_decode, pptbf_domain                 (decode, domain_coords)
//   tiles, point sets, relaxation ...... pptbf_pave_tile, pptbf_own_tile, pptbf_point_sets, pptbf_relaxed,
//                                        pptbf_tile_points                         (tiles_from_codes, point_sets,
//                                                                                   relaxed_sets)
//   per-point draws .................... pptbf_point_seeds                          (point_randoms)
//   ranking ............................ pptbf_rank_distance, pptbf_nearest_threshold (rank_distance, rank_pixels)
//   cell borders ....................... pptbf_border_gather, pptbf_first_exit      (border_table, first_exit)
//   cellular window .................... pptbf_upper_branch, pptbf_cellular_cv     (upper_branch, cellular_cv,
//                                        pptbf_cellular_weight                      cellular_weight)
//   shading ............................ pptbf_window, pptbf_pair_features, pptbf_value (classical_window,
//                                                                                   pair_features, shade)
//
// Precision: all positions are kept relative to an integer cell (the pixel's, a tile's or p0's), so float32
// carries the fractions exactly enough; hashes take floor(m * coordinate) from integer cell + fraction, and where
// numpy's float64 tile centre lies on such a floor boundary in exact arithmetic (centres k/5, k/12 of a cell, the
// thirds of the thirds-bond rows) the float64 arithmetic is repeated exactly in integers (pptbf_x64_*).
// Deviations: V is finally scaled by (1 - 2^-20) (pptbf_V_SCALE): where numpy's V has plateaus (sums of
// identical window values) the float32 sum can land an ulp above numpy's float64 value, which would flip a whole
// plateau sitting exactly at a quantile threshold; the scale keeps such plateaus at or below numpy's value.
// No recursion; loops have constant bounds with early breaks; no division by zero, inf or NaN is relied upon.

#include "pptbf_tables.glsl"

const float pptbf_PI = 3.14159265358979;
const float pptbf_TWO_PI = 6.28318530717959;
const float pptbf_BIG = 1.0e30;          // stands for +inf
const float pptbf_NO_EXIT = 1.35;        // border.NO_EXIT
const float pptbf_V_SCALE = 0.99999905;  // 1 - 2^-20, see the header
const int pptbf_MAXC = 36;               // MAX_CANDIDATES
const int pptbf_MAXN = 18;               // MAX_NEIGHBOURS
const int pptbf_NB = 24;                 // BORDER_NEIGHBOURS

// --------------------------------------------------------------------------------------------------------------
// Hash PRNG and value noise
// --------------------------------------------------------------------------------------------------------------

uint pptbf_seed(int x, int y)
{
    int p0 = pptbf_perm[0];
    int a = pptbf_perm[(x + pptbf_perm[(y + p0) & 1023]) & 1023];
    int b = pptbf_perm[(3 * x + pptbf_perm[(4 * y + p0) & 1023]) & 1023];
    return uint(a + 32768 * b);
}

// n-th draw in [-1, 1): (seed * M^n mod 2^32) / 2^31 - 1, rounded once to float32 (uint arithmetic wraps mod 2^32)
float pptbf_draw(uint s, int n)
{
    uint v = s * pptbf_mpow[n];
    return (v >= 0x80000000u) ? float(v - 0x80000000u) * (1.0 / 2147483648.0)
                              : -float(0x80000000u - v) * (1.0 / 2147483648.0);
}

float pptbf_lattice(int i, int j)
{
    return pptbf_noise[(pptbf_perm[i & 1023] + 3 * pptbf_perm[j & 1023] + 5 * pptbf_perm[0]) & 1023];
}

float pptbf_vnoise(float x, float y)
{
    float fx = floor(x);
    float fy = floor(y);
    int ix = int(fx);
    int iy = int(fy);
    float tx = x - fx;
    float ty = y - fy;
    float sx = tx * tx * (3.0 - 2.0 * tx);
    float sy = ty * ty * (3.0 - 2.0 * ty);
    float l00 = pptbf_lattice(ix, iy);
    float l01 = pptbf_lattice(ix, iy + 1);
    float l10 = pptbf_lattice(ix + 1, iy);
    float l11 = pptbf_lattice(ix + 1, iy + 1);
    float v0 = l00 + (l01 - l00) * sy;
    float v1 = l10 + (l11 - l10) * sy;
    return v0 + (v1 - v0) * sx;
}

// --------------------------------------------------------------------------------------------------------------
// Exact floors of float64 centres: numpy hashes np.floor(m * cx + add) of float64 tile centres. Where m * c is an
// integer in exact arithmetic (c = cell + num/den, e.g. 15 * (ix + 1/5)), numpy's rounding of c decides the seed.
// c64 = c + rho ulp(c) with rho from the table (it depends on the fraction, the sign and the binade of c only);
// the product and the sum are then rounded as float64 does, on small integers (|m c64| = |N| + j ulp(N) / 2).
// --------------------------------------------------------------------------------------------------------------

int pptbf_rhe(float x)           // round half to even (x small)
{
    float r = floor(x + 0.5);
    if (r - x == 0.5 && mod(r, 2.0) != 0.0)
        r -= 1.0;
    return int(r);
}

// floor(m (cell + r) + add) where the value is not on a floor boundary in exact arithmetic (float32 suffices)
int pptbf_hfloor(int cell, float r, int m, int add)
{
    return m * cell + add + int(floor(float(m) * r));
}

// numpy's floor of m * c64 (+ add inside the floor when inside, numpy's floor(fl64(fl64(m c64) + add)); else
// added after) for the exact centre c = cell + num/den of entry ex
int pptbf_xfloor(int cell, int ex, int m, int add, bool inside)
{
    ivec3 rat = pptbf_ex_rat[ex];
    int num = rat.x;
    int den = rat.y;
    int fallback = m * cell + add + int(floor(float(m) * (float(num) / float(den))));
    int N = m * cell + (m * num) / den;
    int cn = cell * den + num;
    bool neg = cn < 0;
    int a16 = (abs(cn) * 16) / den;
    int Ec = findMSB(a16) - 4;       // binade of |c|
    int cross = 0;
    if (rat.z != 0) {
        int a1 = (abs(cn - den / 2) * 16) / den;
        cross = (findMSB(a1) - 4 != Ec) ? 1 : 0;
    }
    float rho = pptbf_ex_rho[ex * 4 * pptbf_rho_binades + ((neg ? pptbf_rho_binades : 0) + clamp(Ec, 0, pptbf_rho_binades - 1)) * 2 + cross];
    int Nm = abs(N);
    int EN = findMSB(Nm);
    float t = float(m) * rho * exp2(float(Ec - EN));
    bool pow2 = (Nm & (Nm - 1)) == 0;
    int j = (t < 0.0 && pow2) ? pptbf_rhe(2.0 * t) : 2 * pptbf_rhe(t);
    int A = neg ? Nm - add : Nm + add;
    int EA = findMSB(max(A, 1));
    int G = 1 << uint(max(EA - EN + 1, 0));
    if (j < 0 && (A & (A - 1)) == 0)
        G = max(G / 2, 1);
    int jj = pptbf_rhe(float(j) / float(G)) * G;
    int after = N - ((neg ? j > 0 : j < 0) ? 1 : 0) + add;
    int within = neg ? -A - ((jj > 0) ? 1 : 0) : A - ((jj < 0) ? 1 : 0);
    bool exact_case = ((m * num) % den == 0) && a16 >= 16 && Ec < pptbf_rho_binades && (!inside || A > 0);
    return exact_case ? (inside ? within : after) : fallback;
}

// floor(m * coordinate + add) of a tile centre or of a point at offset g from an exact centre (ex >= 0)
int pptbf_cfloor(int cell, float r, int ex, float g, int m, int add, bool inside)
{
    if (ex < 0)
        return pptbf_hfloor(cell, r, m, add);
    // a jittered point off the exact centre: the jitter offset decides the side of the boundary
    ivec3 rat = pptbf_ex_rat[ex];
    int mn = m * rat.x;
    int onb = m * cell + add + mn / rat.y + int(floor(float(m) * g));
    int x = pptbf_xfloor(cell, ex, m, add, inside);
    return (g != 0.0 && mn % rat.y == 0) ? onb : ((g != 0.0) ? pptbf_hfloor(cell, r, m, add) : x);
}

// --------------------------------------------------------------------------------------------------------------
// Parameters and coordinates
// --------------------------------------------------------------------------------------------------------------

struct pptbf_Prm {
    int tiling;
    int fam;        // 0 PAVE, 1 CROSS N=2, 2 CROSS N=3, 3 BISQUARE, 4 APAVEMENT
    int shift;
    int relax;
    float psub;
    float randx;
    float randy;
    float jitter;
    float zoom;
    float ca;
    float sa;
    float aspect;
    float dist_a;
    float dist_g;
    float dist_f;
    int shape;
    int nsec;
    float delta;
    float larp;
    float wnorm;
    float smoothness;
    float beta;
    float sigw;
    int mixture;
    float fnorm;
    float corr;
    float aniso;
    int npmin;
    int npmax;
    int kmax;
    float sigcos;
    float sigcosvar;
    int freq;
    float phi;
    float thick;
    float curv;
    float thetamax;
    float F;        // window footprint
    bool cellular;
    int nine;       // 9, from a uniform: the tile loops stay loops (not unrolled into 9 copies)
};

pptbf_Prm pptbf_decode(float prm[29], float ref_width)
{
    pptbf_Prm P;
    P.tiling = clamp(int(prm[1]), 0, 17);
    P.fam = pptbf_tt_family[P.tiling];
    P.shift = pptbf_tt_shift[P.tiling];
    P.relax = pptbf_tt_relax[P.tiling];
    P.psub = pptbf_tt_psub[P.tiling];
    P.randx = pptbf_tt_randx[P.tiling];
    P.randy = pptbf_tt_randy[P.tiling];
    P.jitter = prm[2];
    int res = max(1, int(prm[3]));
    P.zoom = ref_width / float(res);
    float alpha = pptbf_PI * prm[4];
    P.ca = cos(alpha);
    P.sa = sin(alpha);
    P.aspect = (abs(prm[5]) < 1.0e-6) ? 1.0e-6 : prm[5];
    P.dist_a = prm[6];
    P.dist_g = prm[7];
    P.dist_f = prm[8];
    P.shape = clamp(int(prm[9]), 0, 3);
    P.nsec = 1 << uint(clamp(int(floor(max(prm[10], 0.0) + 0.5)), 0, 12));
    P.delta = pptbf_TWO_PI / float(P.nsec);
    P.larp = prm[11];
    P.wnorm = prm[12];
    P.smoothness = prm[13];
    P.beta = prm[14];
    P.sigw = prm[15];
    P.mixture = clamp(int(prm[16]), 0, 5);
    P.fnorm = prm[17];
    P.corr = prm[18];
    P.aniso = prm[19];
    P.npmin = clamp(int(prm[20]), 0, 20);
    P.npmax = clamp(int(prm[21]), 0, 20);
    P.kmax = max(P.npmin, P.npmax);
    P.sigcos = prm[22];
    P.sigcosvar = prm[23];
    P.freq = int(prm[24]);
    P.phi = 0.5 * pptbf_PI * prm[25];
    P.thick = prm[26];
    P.curv = prm[27];
    P.thetamax = pptbf_PI * prm[28];
    P.F = ((P.shape == 0) ? 1.5 : 1.0) * ((P.tiling >= 10) ? 0.4 : 1.0);
    P.cellular = P.beta != 0.0 && P.mixture != 3 && P.mixture != 4;
    P.nine = 9 + min(P.tiling, 0);
    return P;
}

// turbulence then rotation / aspect / zoom: domain units (1 unit = 1 period)
vec2 pptbf_domain(float x0, float y0, pptbf_Prm P)
{
    float x1 = x0;
    float y1 = y0;
    if (P.dist_a != 0.0) {
        float fz = P.dist_f * P.zoom;
        float amp = P.dist_a;
        float m = 0.5;
        for (int o = 0; o < 4; ++o) {
            if (amp != 0.0) {
                x1 += amp * pptbf_vnoise(fz * m * x0 + 2.0, fz * m * y0);
                y1 += amp * pptbf_vnoise(fz * m * x0, fz * m * y0 + 5.0);
            }
            amp *= P.dist_g;
            m *= 2.0;
        }
    }
    return vec2(100.0 + P.zoom * (x1 * P.ca - y1 * P.sa) / P.aspect, 100.0 + P.zoom * (x1 * P.sa + y1 * P.ca));
}

// --------------------------------------------------------------------------------------------------------------
// Tiles and point sets
// --------------------------------------------------------------------------------------------------------------

struct pptbf_Tile {
    ivec2 cell;     // integer cell the tile is expressed in (PAVE: (a, b); tables: the cell owning its centre)
    vec2 c;         // centre relative to the cell
    vec2 h;         // half sizes
    ivec2 ex;       // exact-centre entries of the centre's x, y (-1: float32 exact)
    int own;        // owned-tile index (tables), -1 for PAVE
};

int pptbf_imod(int a, int n)
{
    int r = a - n * (a / n);       // GLSL int division truncates; make the remainder non-negative
    return (r < 0) ? r + n : r;
}

pptbf_Tile pptbf_pave_tile(int a, int b, pptbf_Prm P)
{
    pptbf_Tile t;
    int bm = pptbf_imod(b, P.shift);
    float o = float(bm) / float(P.shift);
    float left = 0.0, right = 0.0, bottom = 0.0, top = 0.0;
    if (P.randx != 0.0) {              // random cuts (types 6-9)
        left = 0.5 * P.randx * pptbf_draw(pptbf_seed(a + 5, b + 10), 1);
        right = 0.5 * P.randx * pptbf_draw(pptbf_seed(a + 6, b + 10), 1);
    }
    if (P.randy != 0.0) {
        bottom = 0.5 * P.randy * pptbf_draw(pptbf_seed(3, b + 10), 1);
        top = 0.5 * P.randy * pptbf_draw(pptbf_seed(3, b + 11), 1);
    }
    float hx = 0.5 * (right + 1.0 - left);
    float hy = 0.5 * (top + 1.0 - bottom);
    t.cell = ivec2(a, b);
    t.c = vec2(o + left + hx, bottom + hy);
    t.h = vec2(hx, hy);
    t.ex = ivec2((P.shift == 3) ? pptbf_third_ex[bm] : -1, -1);
    t.own = -1;
    return t;
}

pptbf_Tile pptbf_own_tile(ivec2 cell, int own)
{
    pptbf_Tile t;
    vec4 o = pptbf_own[own];
    t.cell = cell;
    t.c = o.xy;
    t.h = o.zw;
    t.ex = pptbf_own_ex[own];
    t.own = own;
    return t;
}

// the subdivision of a tile (point_sets): its seed, point count and how it splits; the points come per slot from
// pptbf_slot (valid slots first, numpy's compaction). exact: the centre may be an exact centre (table families).
struct pptbf_Split {
    uint s;
    int n;
    bool single;     // one unsplit cell: the tile itself
    bool s4;
    bool sxs;
    bool sys;
    float fx;        // share of the first part in x / y (1: not split that way)
    float fy;
    int d0;          // the first draw of the slot points
};

pptbf_Split pptbf_split(pptbf_Tile t, float psub, bool exact)
{
    pptbf_Split sp;
    int sx = pptbf_hfloor(t.cell.x, t.c.x, 15, 0);
    int sy = pptbf_hfloor(t.cell.y, t.c.y, 10, 0);
    // (a loop run 0 or 1 times: skipped where no pixel of a SIMD block needs it, which an if is not on llvmpipe)
    for (int once = 0; once < ((exact && (t.ex.x >= 0 || t.ex.y >= 0)) ? 1 : 0); ++once) {
        sx = (t.ex.x >= 0) ? pptbf_xfloor(t.cell.x, t.ex.x, 15, 0, false) : sx;
        sy = (t.ex.y >= 0) ? pptbf_xfloor(t.cell.y, t.ex.y, 10, 0, false) : sy;
    }
    sp.s = pptbf_seed(sx + 10, sy + 3);
    float q = 0.5 * pptbf_draw(sp.s, 1) + 0.5;
    float d2 = pptbf_draw(sp.s, 2);
    float d3 = pptbf_draw(sp.s, 3);
    bool split = psub >= 1.0 || (psub > 0.0 && q < psub);
    float hx = t.h.x, hy = t.h.y;
    sp.s4 = split && abs(hx - hy) < 0.1;
    sp.sxs = split && !sp.s4 && hx > hy + 0.1;
    sp.sys = split && !sp.s4 && !sp.sxs && hy > hx + 0.1;
    sp.single = !(sp.s4 || sp.sxs || sp.sys);
    sp.n = sp.s4 ? 4 : (sp.single ? 1 : 2);
    float cut = 0.4 + 0.2 * (0.5 * d2 + 0.5);
    sp.fx = sp.s4 ? 0.5 + 0.18 * d2 : (sp.sxs ? cut : 1.0);
    sp.fy = sp.s4 ? 0.5 + 0.18 * d3 : (sp.sys ? cut : 1.0);
    sp.d0 = sp.s4 ? 4 : (sp.single ? 2 : 3);
    return sp;
}

// slot k of a split tile, relative to t.cell: cell centre cc, half size ch, off = p* - cc = 0.9 ch u
void pptbf_slot(pptbf_Tile t, pptbf_Split sp, int k, out vec2 cc, out vec2 ch, out vec2 off)
{
    bool right = sp.s4 ? (k & 1) != 0 : (sp.sxs && k == 1);
    bool upper = sp.s4 ? (k & 2) != 0 : (sp.sys && k == 1);
    float hx = t.h.x, hy = t.h.y;
    float chx = (right ? 1.0 - sp.fx : sp.fx) * hx;
    float chy = (upper ? 1.0 - sp.fy : sp.fy) * hy;
    bool bx = sp.s4 || sp.sxs;
    bool by = sp.s4 || sp.sys;
    vec2 lo = t.c - t.h;
    cc = vec2(bx ? lo.x + (right ? 2.0 * sp.fx * hx : 0.0) + chx : t.c.x,
              by ? lo.y + (upper ? 2.0 * sp.fy * hy : 0.0) + chy : t.c.y);
    ch = vec2(bx ? chx : hx, by ? chy : hy);
    off = 0.9 * ch * vec2(pptbf_draw(sp.s, sp.d0 + 2 * k), pptbf_draw(sp.s, sp.d0 + 2 * k + 1));
}

// relaxed p* of the slots of PAVE tile t (types 2, 3; relative to t.cell): its points, moved P.relax times away
// from their 3 nearest among the 9 tiles' points (Jacobi: all movers from the same positions), clamped to their
// cells (relaxed_sets); ok: valid (inside the tile after relaxation)
void pptbf_relax(pptbf_Tile t, pptbf_Split sp, pptbf_Prm P, out vec2 rp[4], out bool ok[4])
{
    vec2 pts[36];                    // the 9 tiles' points (DI / DJ order, 4 slots each), relative to t.cell
    bool val[36];
    for (int c = 0; c < 36; ++c) {
        pts[c] = vec2(0.0);
        val[c] = false;
    }
    // filled as a shift register (constant indices only: an array indexed by a loop variable that is not
    // unrolled lives in memory on llvmpipe, ~25x slower)
    for (int k = 0; k < P.nine; ++k) {
        ivec2 d = ivec2(k % 3 - 1, k / 3 - 1);
        pptbf_Tile tk = pptbf_pave_tile(t.cell.x + d.x, t.cell.y + d.y, P);
        pptbf_Split sk = pptbf_split(tk, P.psub, false);
        for (int c = 0; c < 32; ++c) {
            pts[c] = pts[c + 4];
            val[c] = val[c + 4];
        }
        for (int s = 0; s < 4; ++s) {
            vec2 cc, ch, off;
            pptbf_slot(tk, sk, s, cc, ch, off);
            pts[32 + s] = vec2(d) + cc + off;
            val[32 + s] = s < sk.n;
        }
    }
    vec2 blo = t.c - t.h;
    vec2 bhi = t.c + t.h;
    vec2 lo[4], hi[4], mv[4];
    for (int m = 0; m < 4; ++m) {
        vec2 cc, ch, off;
        pptbf_slot(t, sp, m, cc, ch, off);
        lo[m] = cc - ch + 0.05;
        hi[m] = cc + ch - 0.05;
        mv[m] = cc + off;
    }
    for (int it = 0; it < P.relax; ++it) {
        vec2 moved[4];
        for (int m = 0; m < 4; ++m) {
            vec2 mp = mv[m];
            bool move = m < sp.n && mp.x >= blo.x && mp.x <= bhi.x && mp.y >= blo.y && mp.y <= bhi.y;
            // the 3 nearest other valid points (ties: the lower column)
            float nd0 = pptbf_BIG, nd1 = pptbf_BIG, nd2 = pptbf_BIG;
            vec2 nv0 = vec2(0.0), nv1 = vec2(0.0), nv2 = vec2(0.0);
            for (int kt = 0; kt < 9; ++kt)
            for (int sl = 0; sl < 4; ++sl) {
                int col = 4 * kt + sl;
                vec2 pj = (kt == 4) ? mv[sl] : pts[col];
                vec2 dd = pj - mp;
                float dist = (val[col] && col != 16 + m) ? sqrt(dd.x * dd.x + dd.y * dd.y) : pptbf_BIG;
                bool b0 = dist < nd0, b1 = dist < nd1, b2 = dist < nd2;
                nd2 = b1 ? nd1 : (b2 ? dist : nd2);
                nv2 = b1 ? nv1 : (b2 ? dd : nv2);
                nd1 = b0 ? nd0 : (b1 ? dist : nd1);
                nv1 = b0 ? nv0 : (b1 ? dd : nv1);
                nd0 = b0 ? dist : nd0;
                nv0 = b0 ? dd : nv0;
            }
            float no0 = (nd0 == 0.0) ? 1.0 : nd0;
            float no1 = (nd1 == 0.0) ? 1.0 : nd1;
            float no2 = (nd2 == 0.0) ? 1.0 : nd2;
            vec2 dir = ((nd0 < pptbf_BIG) ? nv0 / (no0 * no0) : vec2(0.0))
                     + ((nd1 < pptbf_BIG) ? nv1 / (no1 * no1) : vec2(0.0))
                     + ((nd2 < pptbf_BIG) ? nv2 / (no2 * no2) : vec2(0.0));
            float nrm = sqrt(dir.x * dir.x + dir.y * dir.y);
            nrm = (nrm == 0.0) ? 1.0 : nrm;
            float nx = min(max(mp.x - dir.x / nrm * 0.05, lo[m].x), hi[m].x);
            float ny = max(mp.y - dir.y / nrm * 0.05, lo[m].y);
            ny = (ny > bhi.y) ? hi[m].y : ny;
            moved[m] = move ? vec2(nx, ny) : mp;
        }
        for (int m = 0; m < 4; ++m)
            mv[m] = moved[m];
    }
    for (int m = 0; m < 4; ++m) {
        rp[m] = mv[m];
        ok[m] = m < sp.n && mv[m].x >= blo.x && mv[m].x <= bhi.x && mv[m].y >= blo.y && mv[m].y <= bhi.y;
    }
}

// a point of a tile: all positions relative to the pixel's cell O
struct pptbf_Pt {
    vec2 pos;        // the jittered point p
    vec2 cc;         // its cell's centre and half size
    vec2 ch;
    vec2 g;          // p - cc
    ivec2 cell;      // its tile's cell
    ivec2 ex;        // exact-centre entries (the single cell of a tile), else -1
    vec2 rel;        // p relative to the tile's cell
    ivec4 id;        // tile cell, owned index (-1 PAVE), slot
};

pptbf_Pt pptbf_point(pptbf_Tile t, pptbf_Split sp, int s, vec2 pstar, bool relaxed, ivec2 O, float J)
{
    pptbf_Pt p;
    vec2 cc, ch, off;
    pptbf_slot(t, sp, s, cc, ch, off);
    off = relaxed ? pstar - cc : off;
    vec2 base = vec2(t.cell - O);
    p.g = J * off;
    p.cc = base + cc;
    p.ch = ch;
    p.pos = p.cc + p.g;
    p.cell = t.cell;
    p.ex = sp.single ? t.ex : ivec2(-1);
    p.rel = cc + p.g;
    p.id = ivec4(t.cell, t.own, s);
    return p;
}

// hash seeds of a point at r = cc + g relative to its tile's cell (g = J (p* - cc)): sa (rotation, kernel count)
// and sb (kernels); ex: the tile's exact-centre entries where the point is its single unsplit cell, else -1
void pptbf_point_seeds(ivec2 cell, ivec2 ex, vec2 r, vec2 g, out uint sa, out uint sb)
{
    int ax = pptbf_cfloor(cell.x, r.x, ex.x, g.x, 12, 7, true);
    int bx = pptbf_cfloor(cell.x, r.x, ex.x, g.x, 15, 2, true);
    int ay = pptbf_cfloor(cell.y, r.y, ex.y, g.y, 12, 1, true);
    int by = pptbf_cfloor(cell.y, r.y, ex.y, g.y, 15, 5, true);
    sa = pptbf_seed(ax, ay);
    sb = pptbf_seed(bx, by);
}

float pptbf_inv_side(float den)
{
    return (den == 0.0) ? pptbf_BIG : 1.0 / den;
}

// inverse distances from a point (at offset g from its cell centre) to its cell sides (left, right, bottom, top)
vec4 pptbf_side_inverses(vec2 g, vec2 ch)
{
    return vec4(pptbf_inv_side(g.x + ch.x), pptbf_inv_side(ch.x - g.x), pptbf_inv_side(g.y + ch.y),
                pptbf_inv_side(ch.y - g.y));
}

// --------------------------------------------------------------------------------------------------------------
// Distances and windows
// --------------------------------------------------------------------------------------------------------------

float pptbf_minkowski(float ax, float ay, float p)
{
    if (p == 2.0)
        return sqrt(ax * ax + ay * ay);
    if (p == 1.0)
        return ax + ay;
    float m = max(ax, ay);
    float n = min(ax, ay);
    if (m <= 0.0)
        return m;
    float r = n / m;
    float rp = (r > 0.0) ? pow(r, p) : 0.0;
    return m * pow(1.0 + rp, 1.0 / p);
}

float pptbf_wnorm(float ax, float ay, float p)
{
    float r = pptbf_minkowski(ax, ay, p);
    if (p > 2.0)
        r = (p - 2.0) * max(ax, ay) + (3.0 - p) * r;
    return r;
}

// ranking distance D from d = q - p, inv = side inverses of p's cell
float pptbf_rank_distance(vec2 d, vec4 inv, float norm, float larp)
{
    float ax = abs(d.x), ay = abs(d.y);
    float r = (larp != 1.0) ? (1.0 - larp) * pptbf_minkowski(ax, ay, norm) : 0.0;
    if (larp != 0.0) {
        float ex = ax * ((d.x < 0.0) ? inv.x : inv.y);
        float ey = ay * ((d.y < 0.0) ? inv.z : inv.w);
        r = r + larp * max(ex, ey);
    }
    return r;
}

float pptbf_window(float r, pptbf_Prm P)
{
    float g;
    if (P.shape <= 1) {
        float eF = exp(-2.0 * P.F);
        g = (exp(-2.0 * r) - eF) / (1.0 - eF);
    } else if (P.shape == 2) {
        g = 1.0 - r / P.F;
    } else {
        g = (r <= P.F) ? 1.0 : 0.0;
    }
    return clamp(g, 0.0, 1.0);
}

// the MAXN nearest candidates by (D, index) (rank_pixels), kept sorted by one compare-and-swap pass per candidate
struct pptbf_Near {
    float d[18];
    float i[18];
};

void pptbf_near_insert(inout pptbf_Near L, float d, float i)
{
    for (int k = 0; k < pptbf_MAXN; ++k) {
        bool sw = d < L.d[k] || (d == L.d[k] && i < L.i[k]);
        float td = L.d[k], ti = L.i[k];
        L.d[k] = sw ? d : td;
        L.i[k] = sw ? i : ti;
        d = sw ? td : d;
        i = sw ? ti : i;
    }
}

// candidate i is among the MAXN nearest iff (D, i) <= the last kept key
bool pptbf_is_near(float i, float di, pptbf_Near L)
{
    float td = L.d[pptbf_MAXN - 1], ti = L.i[pptbf_MAXN - 1];
    return di < td || (di == td && i <= ti);
}

// --------------------------------------------------------------------------------------------------------------
// Cell borders (border.py): the exit of the ray p0 + t e from p0's cell among its BORDER_NEIGHBOURS nearest points
// --------------------------------------------------------------------------------------------------------------

// tile offsets of a 5x5 block from the centre outwards (the nearest points come first)
const ivec2 pptbf_ring[25] = ivec2[25](
    ivec2(0, 0), ivec2(-1, 0), ivec2(1, 0), ivec2(0, -1), ivec2(0, 1), ivec2(-1, -1), ivec2(1, -1), ivec2(-1, 1),
    ivec2(1, 1), ivec2(-2, 0), ivec2(2, 0), ivec2(0, -2), ivec2(0, 2), ivec2(-2, -1), ivec2(2, -1), ivec2(-2, 1),
    ivec2(2, 1), ivec2(-1, -2), ivec2(1, -2), ivec2(-1, 2), ivec2(1, 2), ivec2(-2, -2), ivec2(2, -2), ivec2(-2, 2),
    ivec2(2, 2));

// the pptbf_NB nearest points of p0 by L2, sorted (equal distances keep the earlier): squared distance, position
// relative to p0, side inverses (capped at 1e10 as border_table does)
struct pptbf_Nbrs {
    float d2[24];
    vec2 r[24];
    vec4 inv[24];
};

// insertion by one compare-and-swap pass (constant indices: registers, no indexed memory on llvmpipe)
void pptbf_nbrs_insert(inout pptbf_Nbrs B, vec2 r, vec4 inv)
{
    float d2 = r.x * r.x + r.y * r.y;
    vec4 iv = min(inv, vec4(1.0e10));
    for (int k = 0; k < pptbf_NB; ++k) {
        bool sw = d2 < B.d2[k];
        float td = B.d2[k];
        vec2 tr = B.r[k];
        vec4 ti = B.inv[k];
        B.d2[k] = sw ? d2 : td;
        B.r[k] = sw ? r : tr;
        B.inv[k] = sw ? iv : ti;
        d2 = sw ? td : d2;
        r = sw ? tr : r;
        iv = sw ? ti : iv;
    }
}

// p0's neighbours (border_table) among the points of the tiles around p0's tile (PAVE: 5x5 tiles; table families:
// the owned tiles of 3x3 cells); id0 = p0's tile cell, owned index, slot; p0r = p0 relative to that cell
pptbf_Nbrs pptbf_border_gather(pptbf_Prm P, ivec4 id0, vec2 p0r)
{
    pptbf_Nbrs B;
    for (int k = 0; k < pptbf_NB; ++k) {
        B.d2[k] = pptbf_BIG;
        B.r[k] = vec2(0.0);
        B.inv[k] = vec4(0.0);
    }
    bool pave = P.fam == 0;
    int nown = pave ? 1 : pptbf_fam_nown[P.fam - 1];
    int own0 = pave ? 0 : pptbf_fam_own0[P.fam - 1];
    int ntiles = pave ? 25 : 9 * nown;
    for (int k = 0; k < 9 * pptbf_max_own; ++k) {
        if (k >= ntiles)
            break;
        int kc = k / nown;
        int o = own0 + (k - kc * nown);
        ivec2 d = pptbf_ring[kc];
        pptbf_Tile t;
        if (pave)
            t = pptbf_pave_tile(id0.x + d.x, id0.y + d.y, P);
        else
            t = pptbf_own_tile(id0.xy + d, o);
        // the tile's points lie in its rectangle: skip it when that is beyond the current NB-th nearest
        vec2 gap = max(abs(vec2(d) + t.c - p0r) - t.h, vec2(0.0));
        if (dot(gap, gap) >= B.d2[pptbf_NB - 1])
            continue;
        pptbf_Split sp = pptbf_split(t, P.psub, !pave);
        vec2 rp[4];
        bool rok[4];
        for (int s = 0; s < 4; ++s) {
            rp[s] = vec2(0.0);
            rok[s] = s < sp.n;
        }
        for (int once = 0; once < ((P.relax > 0) ? 1 : 0); ++once)
            pptbf_relax(t, sp, P, rp, rok);
        for (int s = 0; s < 4; ++s) {
            vec2 cc, ch, off;
            pptbf_slot(t, sp, s, cc, ch, off);
            off = (P.relax > 0) ? rp[s] - cc : off;
            vec2 g = P.jitter * off;
            bool self = kc == 0 && t.own == id0.z && s == id0.w;
            vec2 r = vec2(d) + cc + g - p0r;
            if (rok[s] && !self && dot(r, r) < B.d2[pptbf_NB - 1])
                pptbf_nbrs_insert(B, r, pptbf_side_inverses(g, ch));
        }
    }
    return B;
}

// ends (lo, hi) of {s : sqrt(s^2 + p2) + kap s + d0 < 0} (empty: lo = BIG, hi = -BIG); numpy's fmin/fmax drop
// the NaN roots, which is spelled out here
vec2 pptbf_interval_s(float kap, float d0, float p2)
{
    float one_m = 1.0 - kap * kap;
    float d02 = d0 * d0;
    float disc = d02 - one_m * p2;
    float kd = kap * d0;
    float sq = sqrt(max(disc, 0.0));
    float q = kd + ((kd < 0.0) ? -sq : sq);
    float num_b = p2 - d02;
    // r_a = q / one_m, r_b = num_b / q with +-inf for x / 0 and NaN for 0 / 0
    bool a_nan = (one_m == 0.0 && q == 0.0);
    float r_a = (one_m != 0.0) ? q / one_m : ((q > 0.0) ? pptbf_BIG : -pptbf_BIG);
    bool b_nan = (q == 0.0 && num_b == 0.0);
    float r_b = (q != 0.0) ? num_b / q : ((num_b > 0.0) ? pptbf_BIG : -pptbf_BIG);
    float rmin, rmax;
    if (a_nan && b_nan) {
        rmin = 0.0;             // both NaN: the interval is empty below (d0 < 0 and disc > 0 cannot hold)
        rmax = 0.0;
    } else if (a_nan) {
        rmin = r_b;
        rmax = r_b;
    } else if (b_nan) {
        rmin = r_a;
        rmax = r_a;
    } else {
        rmin = min(r_a, r_b);
        rmax = max(r_a, r_b);
    }
    bool dec = kap < -1.0;
    bool inc = kap > 1.0;
    float lo = dec ? rmax : (inc ? -pptbf_BIG : rmin);
    float hi = dec ? pptbf_BIG : (inc ? rmin : rmax);
    bool empty = !(dec || inc) && !((d0 < 0.0) && (disc > 0.0));
    return vec2(empty ? pptbf_BIG : lo, hi);
}

// the smallest t > 0 where the candidate r (relative to p0) is nearer than p0 to t e (BIG: never)
float pptbf_exit_time(vec2 e, vec2 r, vec4 inv, float c0, float larp)
{
    float A = 1.0 - larp;
    float b = e.x * r.x + e.y * r.y;
    float p2 = max(r.x * r.x + r.y * r.y - b * b, 0.0);
    float lo = 0.0;
    float hi = pptbf_BIG;
    float iA = (A > 0.0) ? 1.0 / A : 0.0;
    // the lines of the max (one for larp = 0); a loop with a data-dependent bound, written without arrays, so
    // that it stays one copy
    int nlines = (larp == 0.0) ? 1 : 4;
    for (int m = 0; m < nlines; ++m) {
        // m = 0: +x side (inverse inv.y), 1: -x (inv.x), 2: +y (inv.w), 3: -y (inv.z)
        bool isx = m < 2;
        float sgn = ((m & 1) == 0) ? 1.0 : -1.0;
        float iv = (m == 0) ? inv.y : ((m == 1) ? inv.x : ((m == 2) ? inv.w : inv.z));
        float ec = isx ? e.x : e.y;
        float rc = isx ? r.x : r.y;
        float k = (larp == 0.0) ? -c0 : sgn * larp * iv * ec - c0;
        float c = (larp == 0.0) ? 0.0 : -sgn * larp * iv * rc;
        float l, h;
        if (A > 0.0) {
            float kap = k * iA;
            vec2 lh = pptbf_interval_s(kap, kap * b + c * iA, p2);
            l = (lh.x >= pptbf_BIG) ? pptbf_BIG : lh.x + b;
            h = (lh.y >= pptbf_BIG) ? pptbf_BIG : ((lh.y <= -pptbf_BIG) ? -pptbf_BIG : lh.y + b);
        } else {                 // larp = 1: the line itself
            bool never = (k == 0.0) && (c >= 0.0);
            float root = (k != 0.0) ? -c / k : 0.0;
            l = (k < 0.0) ? root : (never ? pptbf_BIG : -pptbf_BIG);
            h = (k > 0.0) ? root : (never ? -pptbf_BIG : pptbf_BIG);
        }
        lo = max(lo, l);
        hi = min(hi, h);
    }
    return (lo < hi) ? lo : pptbf_BIG;
}

float pptbf_own_slope(vec2 e, vec4 inv0, float larp)
{
    if (larp == 0.0)
        return 1.0;
    float s0x = (e.x < 0.0) ? inv0.x : inv0.y;
    float s0y = (e.y < 0.0) ? inv0.z : inv0.w;
    return (1.0 - larp) + larp * max(abs(e.x) * s0x, abs(e.y) * s0y);
}

// border radii of p0's cell along the sectors ka - 1 .. ka + 2 (angle j delta + delta rot_u), in one pass over
// the neighbours (border._may_win's pruning changes no radius and is left out)
vec4 pptbf_border_radii(int ka, float rot_u, pptbf_Prm P, pptbf_Nbrs B, vec4 inv0)
{
    vec2 e[4];
    float c0[4];
    vec4 best = vec4(pptbf_BIG);
    for (int m = 0; m < 4; ++m) {
        float th = float(ka - 1 + m) * P.delta + P.delta * rot_u;
        e[m] = vec2(cos(th), sin(th));
        c0[m] = pptbf_own_slope(e[m], inv0, P.larp);
    }
    int nb = 0;
    for (int k = 0; k < pptbf_NB; ++k)
        nb += (B.d2[k] < pptbf_BIG) ? 1 : 0;
    // the next neighbour is always at index 0 (a shift register: constant indices, see pptbf_relax)
    for (int k = 0; k < nb; ++k) {
        vec2 r = B.r[0];
        vec4 inv = B.inv[0];
        for (int j = 0; j < pptbf_NB - 1; ++j) {
            B.r[j] = B.r[j + 1];
            B.inv[j] = B.inv[j + 1];
        }
        best.x = min(best.x, pptbf_exit_time(e[0], r, inv, c0[0], P.larp));
        best.y = min(best.y, pptbf_exit_time(e[1], r, inv, c0[1], P.larp));
        best.z = min(best.z, pptbf_exit_time(e[2], r, inv, c0[2], P.larp));
        best.w = min(best.w, pptbf_exit_time(e[3], r, inv, c0[3], P.larp));
    }
    return mix(best, vec4(pptbf_NO_EXIT), greaterThanEqual(best, vec4(pptbf_BIG)));
}

// --------------------------------------------------------------------------------------------------------------
// Cellular window (positions relative to p0)
// --------------------------------------------------------------------------------------------------------------

float pptbf_angle(vec2 d)
{
    float a = (d.x == 0.0 && d.y == 0.0) ? 0.0 : atan(d.y, d.x);
    return mod(a, pptbf_TWO_PI);
}

bool pptbf_upper_branch(float alpha, float ta, float rho_a, float rho_b, float delta)
{
    vec2 A = rho_a * vec2(cos(ta), sin(ta));
    vec2 B = rho_b * vec2(cos(ta + delta), sin(ta + delta));
    float am = pptbf_angle(0.5 * (A + B));
    bool isfar = abs(alpha - am) > 2.0 * delta;
    if (isfar && alpha < 2.0 * delta)
        am -= pptbf_TWO_PI;
    else if (isfar && alpha > pptbf_TWO_PI - 2.0 * delta)
        am += pptbf_TWO_PI;
    return alpha > am;
}

// ray (origin + lam w) / line (A, B) intersection parameter; ok = false where numpy divides by zero
float pptbf_lam(vec2 w, vec2 a, vec2 b, out bool ok)
{
    vec2 u = b - a;
    float n = sqrt(u.x * u.x + u.y * u.y);
    float den0 = w.x * u.y - w.y * u.x;
    ok = n > 0.0 && den0 != 0.0;
    if (!ok)
        return 0.0;
    u /= n;
    return (u.x * (-a.y) - u.y * (-a.x)) / (w.x * u.y - w.y * u.x);
}

// 1 - sdd / r with numpy's -inf for r = 0 (ok = false: NaN or inf, settled by the caller like nan_to_num)
float pptbf_cv_term(float sdd, float r, out bool bad)
{
    bad = !(r != 0.0);
    return bad ? 0.0 : 1.0 - sdd / r;
}

float pptbf_cellular_cv(vec2 d, float rot, int ka, bool up, vec3 rho, pptbf_Prm P)
{
    float sdd = sqrt(d.x * d.x + d.y * d.y);
    if (sdd < 1.0e-4)
        return 1.0;
    float delta = P.delta;
    vec2 w = d / sdd;
    float ta = float(ka) * delta + rot;
    vec2 A = rho.x * vec2(cos(ta), sin(ta));
    vec2 B = rho.y * vec2(cos(ta + delta), sin(ta + delta));
    vec2 M = 0.5 * (A + B);
    float tc = up ? ta + 2.0 * delta : ta - delta;
    vec2 C = rho.z * vec2(cos(tc), sin(tc));
    vec2 N = up ? 0.5 * (B + C) : 0.5 * (A + C);
    vec2 s0 = up ? M : N;
    vec2 s1 = up ? N : M;
    vec2 ctl = up ? B : A;
    bool ok_l, ok_0;
    float lam = pptbf_lam(w, s0, s1, ok_l);
    vec2 S = lam * w;
    vec2 sd = s1 - s0;
    float seg = sqrt(sd.x * sd.x + sd.y * sd.y);
    float t = (seg > 0.0) ? length(S - s0) / seg : 0.0;
    vec2 Qb = (1.0 - t) * (1.0 - t) * s0 + 2.0 * t * (1.0 - t) * ctl + t * t * s1;
    float r0 = pptbf_lam(w, A, B, ok_0);
    float r1 = length(S);
    float r2 = length(Qb);
    bool b0, b1, b2;
    float c0 = pptbf_cv_term(sdd, r0, b0);
    float c1 = pptbf_cv_term(sdd, r1, b1);
    float c2 = pptbf_cv_term(sdd, r2, b2);
    b0 = b0 || !ok_0;
    b1 = b1 || !ok_l || seg == 0.0;
    b2 = b2 || !ok_l || seg == 0.0;
    float sm = P.smoothness;
    float cv;
    bool bad;
    if (sm < 1.0) {
        cv = (1.0 - sm) * c0 + sm * c1;
        bad = b0 || b1;
    } else if (sm < 2.0) {
        cv = (2.0 - sm) * c1 + (sm - 1.0) * c2;
        bad = b1 || b2;
    } else {
        cv = c2;
        bad = b2;
    }
    return bad ? 0.0 : clamp(cv, 0.0, 1.0);
}

float pptbf_cellular_weight(float cv, float sigma)
{
    if (cv <= 0.0)
        return 0.0;
    if (cv >= 1.0)
        return 1.0;
    if (sigma < 1.0e-6)
        return cv;
    float es = exp(-sigma);
    return (exp(sigma * (cv - 1.0)) - es) / (1.0 - es);
}

// --------------------------------------------------------------------------------------------------------------
// Features
// --------------------------------------------------------------------------------------------------------------

float pptbf_stripes(float u, float v, pptbf_Prm P)
{
    if (P.freq == 0)
        return 1.0;
    float cu = P.curv * u;
    float b = 0.5 + 0.5 * cos(pptbf_PI * float(P.freq) * sqrt(cu * cu + v * v));
    return (b > 0.0) ? pow(b, 1.0 / (1.0e-4 + P.thick)) : 0.0;
}

float pptbf_ddist_cut(pptbf_Prm P)
{
    if (P.mixture == 3)
        return 1.0;
    float sp = sin(P.phi);
    if (P.mixture == 1 || (P.mixture == 2 && sp * sp > 1.0e-3))
        return 23.0;
    return 87.0;
}

// kernel sum / max of one (pixel, point) pair (pair_features): q = pixel, p = point, cc / ch its cell, all
// relative to the same origin; mixture 3 returns the priority (-1: none) and its value in val3
float pptbf_pair_features(vec2 q, vec2 p, vec2 cc, vec2 ch, uint sa, uint sb, pptbf_Prm P, out float val3)
{
    int nk = P.npmin + int((float(P.npmax - P.npmin)) * (0.5 * pptbf_draw(sa, 2) + 0.5));
    float acc = (P.mixture == 3) ? -1.0 : 0.0;
    val3 = 0.0;
    float cut = pptbf_ddist_cut(P);
    float sv = exp2(-P.aniso);
    vec2 ih = vec2((ch.x != 0.0) ? 1.0 / ch.x : pptbf_BIG, (ch.y != 0.0) ? 1.0 / ch.y : pptbf_BIG);
    for (int k = 0; k < 20; ++k) {
        if (k >= nk || k >= P.kmax)
            break;
        float kd0 = pptbf_draw(sb, 6 * k + 1);
        float kd1 = pptbf_draw(sb, 6 * k + 2);
        float kd2 = pptbf_draw(sb, 6 * k + 3);
        float kd3 = pptbf_draw(sb, 6 * k + 4);
        float kd4 = pptbf_draw(sb, 6 * k + 5);
        float kd5 = pptbf_draw(sb, 6 * k + 6);
        vec2 l = cc + 0.99 * vec2(kd2, kd3) * ch;
        l = P.corr * p + (1.0 - P.corr) * l;
        float th = P.thetamax * kd4;
        float ct = cos(th), st = sin(th);
        vec2 dl = q - l;
        float u = ih.x * ct * dl.x - ih.y * st * dl.y;
        float v = ih.x * st * sv * dl.x + ih.y * ct * sv * dl.y;
        float s = P.sigcos * (1.0 + (0.5 * kd5 + 0.5) * P.sigcosvar) / P.F;
        float dd = pptbf_wnorm(abs(u), abs(v), P.fnorm) * s;
        if (!(dd < cut))
            continue;
        float ff = pptbf_stripes(u, v, P);
        float e = exp(-dd);
        if (P.mixture == 1) {
            float w = (kd0 < 0.0) ? -0.25 + 0.75 * kd0 : 0.25 + 0.75 * kd0;
            acc += ff * e * w;
        } else if (P.mixture == 2) {
            acc += ff * e;
        } else if (P.mixture == 4) {
            acc = max(acc, ff * e);
        } else {
            float pr = 0.5 * kd1 + 0.5;
            if (dd < 1.0 && ff > 0.5 && pr > acc) {
                acc = pr;
                val3 = 2.0 * (ff - 0.5) * e;
            }
        }
    }
    return acc;
}

// --------------------------------------------------------------------------------------------------------------
// The entry point
// --------------------------------------------------------------------------------------------------------------

// the candidate tiles of the pixel's cell O (sub-cell code row code0): PAVE the 3x3 tiles, tables the code's 9
pptbf_Tile pptbf_cand_tile(pptbf_Prm P, ivec2 O, int code0, int k)
{
    if (P.fam == 0)
        return pptbf_pave_tile(O.x + k % 3 - 1, O.y + k / 3 - 1, P);
    ivec3 row = pptbf_code[code0 + k];
    return pptbf_own_tile(O + row.xy, row.z);
}

// Raw PPTBF value V at base coordinates (x0, y0) = pixel / (ref_width * pixel_scale) + shift, as
// pptbf.base_coords gives them; prm = the 29-vector (pptbf.PARAM_NAMES order); ref_width as in pptbf.evaluate.
// key: the cell the pixel is in, pptbf.cell_keys of its closest point / 2^24 (exact in float32).
// distance (reference widths, inside > 0) from d (relative to p0) to the polygon of p0's cell through the border
// points of sectors ka - 3 .. ka + 4, measured in the image (pptbf.border_distance, BORDER_FAN = 3)
float pptbf_border_distance(vec2 d, int ka, float rot_u, pptbf_Prm P, pptbf_Nbrs B, vec4 inv0)
{
    vec4 lo = pptbf_border_radii(ka - 2, rot_u, P, B, inv0);     // sectors ka - 3 .. ka
    vec4 hi = pptbf_border_radii(ka + 2, rot_u, P, B, inv0);     // sectors ka + 1 .. ka + 4
    float rho[8] = float[8](lo.x, lo.y, lo.z, lo.w, hi.x, hi.y, hi.z, hi.w);
    vec2 V[8];
    for (int k = 0; k < 8; ++k) {
        float t = float(ka - 3 + k) * P.delta + P.delta * rot_u;
        V[k] = rho[k] * vec2(cos(t), sin(t));
    }
    float best = pptbf_BIG;
    for (int k = 0; k < 7; ++k) {
        vec2 e = V[k + 1] - V[k];
        float side = e.x * (d.y - V[k].y) - e.y * (d.x - V[k].x);     // > 0 inside (counter-clockwise sides)
        float across = P.zoom * length(vec2(e.y / P.aspect, e.x));      // domain -> image across the side
        if (across > 0.0)
            best = min(best, side / across);
    }
    return best;
}

// V, or with border the distance to the closest point's cell border (pptbf.evaluate's field)
float pptbf_eval_field(float x0, float y0, float ref_width, float prm[29], bool border, out float key)
{
    key = 0.0;
    pptbf_Prm P = pptbf_decode(prm, ref_width);
    vec2 xy = pptbf_domain(x0, y0, P);
    vec2 fl = floor(xy);
    ivec2 O = ivec2(fl);
    vec2 q = xy - fl;                    // the pixel relative to its cell O
    int code0 = 0;
    if (P.fam != 0) {
        int n = pptbf_fam_n[P.fam - 1];
        int qx = clamp(int(floor(q.x * float(n))), 0, n - 1);
        int qy = clamp(int(floor(q.y * float(n))), 0, n - 1);
        code0 = pptbf_fam_code0[P.fam - 1] + (qx * n + qy) * 9;
    }
    bool relaxed = P.relax > 0;

    // pass 1: the candidates (the 9 tiles' points, index 4 tile + slot: numpy's order of the valid ones), their
    // ranking distance D, the closest p0 (ties: the lower index) and the MAXN nearest
    pptbf_Near L;
    for (int k = 0; k < pptbf_MAXN; ++k) {
        L.d[k] = pptbf_BIG;
        L.i[k] = 1000.0;
    }
    vec2 rstar[36];                      // relaxed p* (relaxed types), reused by pass 2 (a shift register)
    for (int c = 0; c < 36; ++c)
        rstar[c] = vec2(0.0);
    pptbf_Pt p0 = pptbf_Pt(vec2(0.0), vec2(0.0), vec2(0.0), vec2(0.0), ivec2(0), ivec2(-1), vec2(0.0), ivec4(0));
    float D0 = pptbf_BIG;
    float i0 = -1.0;
    for (int k = 0; k < P.nine; ++k) {
        pptbf_Tile t = pptbf_cand_tile(P, O, code0, k);
        pptbf_Split sp = pptbf_split(t, P.psub, true);
        vec2 rp[4];
        bool rok[4];
        for (int s = 0; s < 4; ++s) {
            rp[s] = vec2(0.0);
            rok[s] = s < sp.n;
        }
        for (int once = 0; once < (relaxed ? 1 : 0); ++once) {
            pptbf_relax(t, sp, P, rp, rok);
            for (int c = 0; c < 32; ++c)
                rstar[c] = rstar[c + 4];
            for (int s = 0; s < 4; ++s)
                rstar[32 + s] = rok[s] ? rp[s] : vec2(pptbf_BIG);
        }
        for (int s = 0; s < 4; ++s) {
            pptbf_Pt p = pptbf_point(t, sp, s, rp[s], relaxed, O, P.jitter);
            vec4 inv = (P.larp != 0.0) ? pptbf_side_inverses(p.g, p.ch) : vec4(0.0);
            float D = rok[s] ? pptbf_rank_distance(q - p.pos, inv, P.wnorm, P.larp) : pptbf_BIG;
            float idx = float(4 * k + s);
            bool better = D < D0;
            D0 = better ? D : D0;
            i0 = better ? idx : i0;
            p0 = better ? p : p0;
            if (rok[s])
                pptbf_near_insert(L, D, idx);
        }
    }
    if (i0 < 0.0)
        return 0.0;
    uint sa0, sb0;
    pptbf_point_seeds(p0.cell, p0.ex, p0.rel, p0.g, sa0, sb0);
    key = float((sa0 * pptbf_mpow[3]) >> 8u) * (1.0 / 16777216.0);

    // the cellular window of p0
    bool mix34 = P.mixture == 3 || P.mixture == 4;
    float wcell = 0.0;
    if (P.cellular) {
        float rot_u = 0.5 * pptbf_draw(sa0, 1) + 0.5;
        float rot = P.delta * rot_u;
        vec2 d = q - p0.pos;
        float alpha = pptbf_angle(d);
        float palpha = alpha - rot;
        if (palpha < 0.0)
            palpha += pptbf_TWO_PI;
        int ka = int(floor(palpha / P.delta));
        vec2 p0r = p0.pos - vec2(p0.id.xy - O);
        pptbf_Nbrs B = pptbf_border_gather(P, p0.id, p0r);
        vec4 inv0 = min(pptbf_side_inverses(p0.g, p0.ch), vec4(1.0e10));
        if (border)
            return pptbf_border_distance(d, ka, rot_u, P, B, inv0);
        vec4 rho = pptbf_border_radii(ka, rot_u, P, B, inv0);      // sectors ka - 1 .. ka + 2
        float ta = float(ka) * P.delta + rot;
        bool up = pptbf_upper_branch(alpha, ta, rho.y, rho.z, P.delta);
        float cv = pptbf_cellular_cv(d, rot, ka, up, vec3(rho.y, rho.z, up ? rho.w : rho.x), P);
        wcell = P.beta * pptbf_cellular_weight(cv, P.sigw);
    }

    if (border)
        return 0.0;                      // no cellular window: no border (the graph refuses it)

    // pass 2: windows and features of the MAXN nearest
    float ws = 0.0;
    float V = 0.0;
    float cp = cos(P.phi), sp2 = sin(P.phi);
    cp *= cp;
    sp2 *= sp2;
    float top = -1.0;
    for (int k = 0; k < P.nine; ++k) {
        pptbf_Tile t = pptbf_cand_tile(P, O, code0, k);
        pptbf_Split sp = pptbf_split(t, P.psub, true);
        vec2 rs4[4];
        for (int s = 0; s < 4; ++s)
            rs4[s] = rstar[s];
        for (int once = 0; once < (relaxed ? 1 : 0); ++once) {
            for (int c = 0; c < 32; ++c)
                rstar[c] = rstar[c + 4];
        }
        for (int s = 0; s < 4; ++s) {
            float idx = float(4 * k + s);
            vec2 rs = rs4[s];
            bool valid = relaxed ? rs.x < pptbf_BIG : s < sp.n;
            pptbf_Pt p = pptbf_point(t, sp, s, rs, relaxed, O, P.jitter);
            vec4 inv = (P.larp != 0.0) ? pptbf_side_inverses(p.g, p.ch) : vec4(0.0);
            float D = pptbf_rank_distance(q - p.pos, inv, P.wnorm, P.larp);
            bool near = valid && pptbf_is_near(idx, D, L);
            vec2 dq = q - p.pos;
            float g = pptbf_window(pptbf_wnorm(abs(dq.x), abs(dq.y), P.wnorm), P);
            float w = (near && !mix34) ? (1.0 - P.beta) * g : 0.0;
            w += (idx == i0) ? wcell : 0.0;
            ws += w;
            bool pair = (P.mixture >= 1 && P.mixture <= 4) && (mix34 ? near : w != 0.0);
            for (int once = 0; once < (pair ? 1 : 0); ++once) {
                uint sa, sb;
                pptbf_point_seeds(p.cell, p.ex, p.rel, p.g, sa, sb);
                float val3;
                float f = pptbf_pair_features(q, p.pos, p.cc, p.ch, sa, sb, P, val3);
                if (P.mixture == 1 || P.mixture == 2) {
                    float F = (P.mixture == 1) ? 0.5 + 0.5 * f : f / float(max(P.npmax / 2, 1));
                    V += w * (F * cp + (1.0 - F) * sp2);
                } else if (P.mixture == 4) {
                    V = max(V, f);
                } else if (f >= 0.0 && f > top) {
                    top = f;             // the first pair with the top priority
                    V = val3;
                }
            }
        }
    }
    if (P.mixture == 0 || P.mixture == 5)
        V = (P.mixture == 5) ? ws * cp : ws;
    if (!mix34 && P.shape == 0 && ws > 0.0)
        V = (P.mixture == 0) ? 1.0 : V / ws;
    return max(V, 0.0) * pptbf_V_SCALE;
}

float pptbf_eval(float x0, float y0, float ref_width, float prm[29], out float key)
{
    return pptbf_eval_field(x0, y0, ref_width, prm, false, key);
}

// the PPTBF value V alone
float pptbf_value(float x0, float y0, float ref_width, float prm[29])
{
    float key;
    return pptbf_eval(x0, y0, ref_width, prm, key);
}

// the distance to the closest point's cell border alone (pptbf.evaluate with field="border")
float pptbf_border(float x0, float y0, float ref_width, float prm[29])
{
    float key;
    bool border = prm[1] > -1.0;         // true, but not a constant: with a literal true llvmpipe returned 0
    return pptbf_eval_field(x0, y0, ref_width, prm, border, key);
}

// the cell key alone (pptbf.cell_keys of the closest point / 2^24)
float pptbf_cell(float x0, float y0, float ref_width, float prm[29])
{
    float key;
    float v = pptbf_eval(x0, y0, ref_width, prm, key);
    return (v >= 0.0) ? key : 0.0;     // (V >= 0 always; without a use of V, Mesa 22 drops the key too)
}
