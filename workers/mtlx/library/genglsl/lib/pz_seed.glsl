// proceduralize: the realisation offset of a node for a document seed (0 = the exported realisation).
// An integer hash (murmur3 finaliser) of (seed, stream) -> two numbers in [0, 1); seed 0 gives (0, 0).
uint pz_mix(uint h)
{
    h ^= h >> 16u;
    h *= 0x85ebca6bu;
    h ^= h >> 13u;
    h *= 0xc2b2ae35u;
    h ^= h >> 16u;
    return h;
}

vec2 pz_seed_offset(int seed, int stream)
{
    if (seed == 0)
        return vec2(0.0);
    uint h = pz_mix(uint(seed) * 0x9e3779b9u + pz_mix(uint(stream)));
    uint g = pz_mix(h ^ 0x68e31da4u);
    return vec2(float(h >> 8u), float(g >> 8u)) / 16777216.0;
}

// Per-cell draws, as workers.nodes.instances draws them in numpy: a cell key (24-bit integer, carried as
// key / 2^24 in a float), the node's stream (its seed at the exported realisation, moved by the document seed)
// and a draw index k.
uint pz_stream(int stream, int seed)
{
    uint s = uint(stream);
    return seed == 0 ? s : s ^ pz_mix(uint(seed));
}

uint pz_cell_hash(float cells, uint stream, uint k)
{
    uint key = uint(round(cells * 16777216.0));
    return pz_mix(key * 0x9e3779b9u + pz_mix(stream + 0x632be5abu * k));
}

float pz_cell_uniform(float cells, uint stream, uint k)
{
    return float(pz_cell_hash(cells, stream, k) >> 8u) / 16777216.0;
}

float pz_cell_normal(float cells, uint stream, uint k)
{
    float u1 = (float(pz_cell_hash(cells, stream, 2u * k) >> 8u) + 0.5) / 16777216.0;
    float u2 = pz_cell_uniform(cells, stream, 2u * k + 1u);
    return sqrt(-2.0 * log(u1)) * cos(6.283185307179586 * u2);
}
