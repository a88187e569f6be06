// One byte of a radix selection by a workgroup of 256 invocations, shared by ridge.wgsl
// (each scale's noise median) and spectrum.wgsl (the white-noise median above the band):
// the host appends this file to each. A pass empties the histogram (`select_clear`), has
// every invocation count the values still in the running into it (`select_count`, the
// byte of each), and takes the byte whose running count first passes the rank
// (`select_byte`), which then counts from that byte's first value.

var<workgroup> select_bins: array<atomic<u32>, 256>;
var<workgroup> select_sums: array<u32, 256>;
var<workgroup> select_chosen: vec2<u32>;

// Empties the histogram; every invocation calls it, in uniform control flow.
fn select_clear(lid: u32) {
    atomicStore(&select_bins[lid], 0u);
    workgroupBarrier();
}

// Counts one value whose byte is `byte`.
fn select_count(byte: u32) {
    atomicAdd(&select_bins[byte & 255u], 1u);
}

// The byte whose running count first passes `rank`, and the rank left within it; every
// invocation calls it, in uniform control flow, once all have counted.
fn select_byte(lid: u32, rank: u32) -> vec2<u32> {
    workgroupBarrier();
    // Running sums over the 256 bytes (one an invocation), doubling the reach.
    let own = atomicLoad(&select_bins[lid]);
    select_sums[lid] = own;
    workgroupBarrier();
    for (var reach = 1u; reach < 256u; reach = reach << 1u) {
        var add = 0u;
        if (lid >= reach) {
            add = select_sums[lid - reach];
        }
        workgroupBarrier();
        select_sums[lid] = select_sums[lid] + add;
        workgroupBarrier();
    }
    let through = select_sums[lid];
    if (own > 0u && through - own <= rank && rank < through) {
        select_chosen = vec2<u32>(lid, rank - (through - own));
    }
    return workgroupUniformLoad(&select_chosen);
}
