#include "lib/pz_seed.glsl"

// proceduralize: 1 where the pixel is inside parent and its cell drew a number in [lo, hi) (one kind of an
// instance split: the kinds' [lo, hi) partition [0, 1) by their shares), else 0.
void mx_cell_kind_float(float cells, float parent, int seed, int stream, float lo, float hi, out float result)
{
    float u = pz_cell_uniform(cells, pz_stream(stream, seed), 0u);
    result = (parent > 0.5 && u >= lo && u < hi) ? 1.0 : 0.0;
}
