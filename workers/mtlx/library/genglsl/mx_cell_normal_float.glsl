#include "lib/pz_seed.glsl"

// proceduralize: the k-th standard normal draw of the pixel's cell (per-piece offsets).
void mx_cell_normal_float(float cells, int seed, int stream, int k, out float result)
{
    result = pz_cell_normal(cells, pz_stream(stream, seed), uint(k));
}
