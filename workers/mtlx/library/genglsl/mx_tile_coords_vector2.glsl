#include "lib/pz_seed.glsl"

// proceduralize: texture coordinates of a baked periodic tile (tile_size pixels) for the pixel at texcoord of a
// size-pixel image, moved by offset pixels, zoomed by scale about the top-left corner (as the procedural nodes
// are), and translated by the seed's offset. At scale 1, seed 0 and tile_size = size it is texcoord itself.
void mx_tile_coords_vector2(vec2 texcoord, vec2 offset, vec2 size, vec2 tile_size, float scale, int seed,
                            int stream, out vec2 result)
{
    float i = (texcoord.x * size.x - 0.5 + offset.x) / scale + 0.5;
    float j = ((1.0 - texcoord.y) * size.y - 0.5 + offset.y) / scale + 0.5;
    vec2 o = pz_seed_offset(seed, stream);
    result = vec2(i / tile_size.x + o.x, 1.0 - j / tile_size.y - o.y);
}
