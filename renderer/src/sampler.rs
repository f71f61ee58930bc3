//! Random numbers keyed on what they are for, never on who draws them.
//!
//! Every value is a function of (seed, pixel, sample index, dimension), where the dimension
//! is fixed by the bounce and the purpose of the draw: a point of a scrambled Sobol
//! sequence ([`Sampler`]). A pixel therefore gets the same numbers
//! whichever thread, tile, subscreen or node renders it, which is what makes images
//! byte-identical across every way of dividing the work.

use crate::simd::U32x8;

/// Dimensions reserved per bounce. Draws within a bounce past this budget spill into the
/// next bounce's range only if an integrator uses more than this many, which none does.
pub const DIMS_PER_BOUNCE: u32 = 16;
/// Dimensions reserved for the camera (pixel position, lens).
const CAMERA_DIMS: u32 = 4;
/// The dimension of the sample's position within its pixel ([`Sampler::pixel_2d`]).
pub const PIXEL_DIM: u32 = 0;

#[inline(always)]
fn mix64(mut z: u64) -> u64 {
    // splitmix64 finaliser: a bijection with full avalanche.
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Reverses the order of the bits of a 32-bit word.
#[inline(always)]
fn reverse(x: u32) -> u32 {
    x.reverse_bits()
}

/// Reverses the bits of two words in one 64-bit reversal: (reverse(a), reverse(b)). x86-64
/// has no bit-reversal instruction, so each reversal is a byte swap and three rounds of
/// masks and shifts; a 2D draw's two coordinates share theirs.
#[inline(always)]
fn reverse_pair(a: u32, b: u32) -> (u32, u32) {
    let r = ((a as u64) << 32 | b as u64).reverse_bits();
    (r as u32, (r >> 32) as u32)
}

/// A hash that only carries each bit into more significant ones (Laine and Karras 2011),
/// so that applied to bit-reversed numbers it is an Owen scrambling: each digit of the
/// fraction is flipped or not according to the digits before it. (Owen scrambling of a
/// fraction `x` given as 32 bits, most significant first, is `reverse(laine_karras(
/// reverse(x), seed))`, Burley 2020; the draws below fold neighbouring reversals away.)
#[inline(always)]
fn laine_karras(mut x: u32, seed: u32) -> u32 {
    x = x.wrapping_add(seed);
    for m in LAINE_KARRAS_FACTORS {
        x ^= x.wrapping_mul(m);
    }
    x
}

const LAINE_KARRAS_FACTORS: [u32; 4] = [0x6c50_b47c, 0xb82f_1e52, 0xc7af_e638, 0x8d22_f6e6];

/// [`laine_karras`] on eight lanes.
#[inline(always)]
fn laine_karras8(x: U32x8, seed: u32) -> U32x8 {
    let mut x = x.wrapping_add(U32x8::splat(seed));
    for m in LAINE_KARRAS_FACTORS {
        x = x.xor(x.wrapping_mul(U32x8::splat(m)));
    }
    x
}

/// The generator matrix columns of a Sobol dimension, most significant bit first, from its
/// primitive polynomial (degree `degree`, inner coefficients `coefficients`, highest power
/// first) and initial direction numbers `m` (Joe and Kuo's table: `s`, `a`, `m_i`).
const fn sobol_columns(degree: usize, coefficients: u32, m: [u32; 3]) -> [u32; 32] {
    let mut v = [0u32; 32];
    let mut k = 0;
    while k < 32 {
        if k < degree {
            v[k] = m[k] << (31 - k);
        } else {
            let mut x = v[k - degree] ^ (v[k - degree] >> degree);
            let mut j = 1;
            while j < degree {
                if (coefficients >> (degree - 1 - j)) & 1 != 0 {
                    x ^= v[k - j];
                }
                j += 1;
            }
            v[k] = x;
        }
        k += 1;
    }
    v
}

/// For each byte of an index and each value of that byte, the XOR of the bit-reversed
/// columns its set bits select: a reversed point of the dimension is four lookups.
type ReversedTable = [[u32; 256]; 4];

const fn reversed_table(columns: [u32; 32]) -> ReversedTable {
    let mut table = [[0u32; 256]; 4];
    let mut byte = 0;
    while byte < 4 {
        let mut value = 0;
        while value < 256 {
            let mut x = 0;
            let mut bit = 0;
            while bit < 8 {
                if value & (1 << bit) != 0 {
                    x ^= columns[8 * byte + bit].reverse_bits();
                }
                bit += 1;
            }
            table[byte][value] = x;
            value += 1;
        }
        byte += 1;
    }
    table
}

/// The Sobol sequence's second dimension (the first is the bit reversal of the index): the
/// polynomial x + 1, whose columns are Pascal's triangle mod 2.
static SOBOL_SECOND_REVERSED: ReversedTable = reversed_table(sobol_columns(1, 0, [1, 0, 0]));
/// Its third and fourth (x^2 + x + 1 and x^3 + x + 1), for draws that continue a 2D draw into
/// four dimensions ([`Sampler::get_2d_after`]).
static SOBOL_THIRD_REVERSED: ReversedTable = reversed_table(sobol_columns(2, 1, [1, 3, 0]));
static SOBOL_FOURTH_REVERSED: ReversedTable = reversed_table(sobol_columns(3, 1, [1, 3, 1]));

/// The bit reversal of a Sobol dimension's point at `index`.
#[inline(always)]
fn sobol_reversed(table: &ReversedTable, index: u32) -> u32 {
    let [b0, b1, b2, b3] = index.to_le_bytes();
    table[0][b0 as usize] ^ table[1][b1 as usize] ^ table[2][b2 as usize] ^ table[3][b3 as usize]
}

/// [`sobol_reversed`] on eight lanes.
#[inline(always)]
fn sobol_reversed8(table: &ReversedTable, index: U32x8) -> U32x8 {
    index
        .lookup(&table[0])
        .xor(index.shr::<8>().lookup(&table[1]))
        .xor(index.shr::<16>().lookup(&table[2]))
        .xor(index.shr::<24>().lookup(&table[3]))
}

/// 32 bits of fraction as an f32 in [0, 1).
#[inline(always)]
fn unit(x: u32) -> f32 {
    (x >> 8) as f32 * (1.0 / (1u32 << 24) as f32)
}

/// Dimensions whose seeds a [`PixelSeeds`] keeps: the camera's and those of the first eight
/// bounces, which is where nearly all draws of a path are (Russian roulette ends most paths
/// before); draws beyond work their seeds out each time.
const CACHED_DIMS: usize = (CAMERA_DIMS + 8 * DIMS_PER_BOUNCE) as usize;

/// The seeds of one dimension (shuffle, scramble x, scramble y) and a last word that is 1
/// once they have been worked out.
type DimSeeds = [u32; 4];

/// What a pixel's samples share: the hash of (seed, pixel), and the seeds of each dimension,
/// worked out on the first draw of that dimension and kept for the pixel's other samples
/// (two splitmix64 rounds a draw otherwise, a tenth of what a sample's draws cost). Only
/// a cache: the numbers are those of [`Sampler::new`].
pub struct PixelSeeds {
    pixel: u64,
    dims: [std::cell::Cell<DimSeeds>; CACHED_DIMS],
}

impl PixelSeeds {
    pub fn new(seed: u64, px: u32, py: u32) -> PixelSeeds {
        PixelSeeds {
            pixel: pixel_hash(seed, px, py),
            dims: std::array::from_fn(|_| std::cell::Cell::new([0; 4])),
        }
    }

    /// Sample `sample` of this pixel: the numbers of `Sampler::new(seed, px, py, sample)`.
    #[inline]
    pub fn sampler(&self, sample: u32) -> Sampler<'_> {
        self.sampler_reversed(sample, reverse(sample))
    }

    /// [`PixelSeeds::sampler`] for a sample whose bit reversal is known.
    #[inline(always)]
    fn sampler_reversed(&self, sample: u32, sample_reversed: u32) -> Sampler<'_> {
        Sampler {
            pixel: self.pixel,
            cache: &self.dims,
            sample,
            sample_reversed,
            dim: 0,
        }
    }
}

/// The first dimension of bounce `bounce`.
#[inline(always)]
fn bounce_dim(bounce: u32) -> u32 {
    CAMERA_DIMS + bounce.saturating_mul(DIMS_PER_BOUNCE)
}

fn pixel_hash(seed: u64, px: u32, py: u32) -> u64 {
    let pixel = ((py as u64) << 32) | px as u64;
    mix64(mix64(seed ^ 0x6a09_e667_f3bc_c909) ^ pixel)
}

/// The seeds of dimension `dim` of the pixel of hash `pixel`.
#[inline(always)]
fn dim_seeds(pixel: u64, dim: u32) -> DimSeeds {
    let h = mix64(pixel ^ (dim as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15));
    let h2 = mix64(h);
    [h as u32, (h >> 32) as u32, h2 as u32, 1]
}

/// The seeds of dimension `dim` of the pixel of hash `pixel`, from `cache` where they were
/// kept (and kept there once worked out).
#[inline(always)]
fn kept_seeds(cache: &[std::cell::Cell<DimSeeds>], pixel: u64, dim: u32) -> DimSeeds {
    match cache.get(dim as usize) {
        Some(cell) => {
            let cached = cell.get();
            if cached[3] != 0 {
                cached
            } else {
                let fresh = dim_seeds(pixel, dim);
                cell.set(fresh);
                fresh
            }
        }
        None => dim_seeds(pixel, dim),
    }
}

/// The numbers of one sample of one pixel.
///
/// Each draw (a 1D value or a 2D pair, at a fixed dimension) is a point of an Owen-scrambled
/// Sobol sequence (Burley 2020, "Practical hash-based Owen scrambling"): the pixel's samples
/// are the sequence's points in an order shuffled per pixel and per dimension, each
/// coordinate scrambled per pixel and per dimension. So the first N samples of a pixel are
/// stratified in every 2D projection a draw uses (better than independent numbers, most of
/// all at powers of two), while different dimensions and pixels stay uncorrelated. The
/// shuffle and scramble seeds are hashes of (seed, pixel, dimension), the index is the
/// sample's: nothing depends on who renders the pixel.
#[derive(Clone, Copy, Debug)]
pub struct Sampler<'a> {
    /// Hash of (seed, pixel).
    pixel: u64,
    /// Seeds of the pixel's first dimensions, shared by its samples (empty: none kept).
    cache: &'a [std::cell::Cell<DimSeeds>],
    sample: u32,
    /// The sample index, bit-reversed (the first step of shuffling it).
    sample_reversed: u32,
    dim: u32,
}

/// What keys the draws of one sample that are not tied to a dimension ([`Sampler::keyed`]):
/// small enough to travel with every ray the sample casts.
#[derive(Clone, Copy, Debug)]
pub struct SampleKey(u64);

impl SampleKey {
    /// See [`Sampler::keyed`].
    #[inline]
    pub fn keyed(self, bounce: u32, a: u32, b: u32) -> f32 {
        let h = mix64(
            self.0
                ^ mix64(
                    ((bounce as u64) << 32 | a as u64) ^ mix64(b as u64 ^ 0xa5a5_5a5a_dead_beef),
                ),
        );
        (h >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
    }
}

impl Sampler<'static> {
    /// A sample on its own, keeping no seeds for others (see [`PixelSeeds`] for a pixel's).
    pub fn new(seed: u64, px: u32, py: u32, sample: u32) -> Sampler<'static> {
        Sampler {
            pixel: pixel_hash(seed, px, py),
            cache: &[],
            sample,
            sample_reversed: reverse(sample),
            dim: 0,
        }
    }
}

impl Sampler<'_> {
    /// Moves to the dimensions of bounce `bounce` (0 = the camera ray's first hit).
    #[inline]
    pub fn start_bounce(&mut self, bounce: u32) {
        self.dim = bounce_dim(bounce);
    }

    /// The seeds of the current dimension, and a step to the next: (shuffle, scramble x,
    /// scramble y).
    #[inline(always)]
    fn seeds(&mut self) -> (u32, u32, u32) {
        let dim = self.dim;
        self.dim = self.dim.wrapping_add(1);
        let [shuffle, sx, sy, _] = self.seeds_of(dim);
        (shuffle, sx, sy)
    }

    /// The seeds of dimension `dim`, from the pixel's kept ones where they are.
    #[inline(always)]
    fn seeds_of(&self, dim: u32) -> DimSeeds {
        kept_seeds(self.cache, self.pixel, dim)
    }

    /// The sample's index in this dimension's order: the Owen scrambling of its index.
    #[inline(always)]
    fn shuffled(&self, shuffle: u32) -> u32 {
        reverse(laine_karras(self.sample_reversed, shuffle))
    }

    /// Uniform in [0, 1).
    #[inline]
    pub fn get_1d(&mut self) -> f32 {
        let (shuffle, sx, _) = self.seeds();
        // The first Sobol dimension is the reversed index; scrambled, reversed back.
        unit(reverse(laine_karras(self.shuffled(shuffle), sx)))
    }

    #[inline]
    pub fn get_2d(&mut self) -> (f32, f32) {
        let (shuffle, sx, sy) = self.seeds();
        let index = self.shuffled(shuffle);
        let (x, y) = reverse_pair(
            laine_karras(index, sx),
            laine_karras(sobol_reversed(&SOBOL_SECOND_REVERSED, index), sy),
        );
        (unit(x), unit(y))
    }

    /// A 2D draw that carries the 2D draw made at dimension `first` on into four dimensions:
    /// the same shuffled index as that draw, at the Sobol sequence's third and fourth
    /// dimensions, scrambled with this dimension's seeds. So the first N samples of a pixel
    /// are stratified over the four numbers together, not only pair by pair, where the two
    /// draws feed one integrand (a bounce's direction and the light sample where it lands:
    /// 4% lower relMSE on the Cornell box at 256 spp, 6% at 1024). `first` is a dimension
    /// drawn earlier by `get_2d` (or `pixel_2d`).
    #[inline]
    pub fn get_2d_after(&mut self, first: u32) -> (f32, f32) {
        let (_, sx, sy) = self.seeds();
        let index = self.shuffled(self.seeds_of(first)[0]);
        let (x, y) = reverse_pair(
            laine_karras(sobol_reversed(&SOBOL_THIRD_REVERSED, index), sx),
            laine_karras(sobol_reversed(&SOBOL_FOURTH_REVERSED, index), sy),
        );
        (unit(x), unit(y))
    }

    /// The dimension the next draw takes.
    #[inline]
    pub fn dim(&self) -> u32 {
        self.dim
    }

    /// The position of the sample within its pixel.
    #[inline]
    pub fn pixel_2d(&mut self) -> (f32, f32) {
        self.dim = PIXEL_DIM;
        self.get_2d()
    }

    /// What [`SampleKey::keyed`] needs of this sample.
    #[inline]
    pub fn key(&self) -> SampleKey {
        SampleKey(mix64(self.pixel ^ self.sample as u64))
    }

    /// A value keyed on this sample and on arbitrary ids rather than on the dimension
    /// budget, for draws whose number is open-ended (stochastic transparency: one per
    /// surface crossed) or whose order is not fixed (traversal visits surfaces in any order).
    #[inline]
    pub fn keyed(&self, bounce: u32, a: u32, b: u32) -> f32 {
        self.key().keyed(bounce, a, b)
    }
}

/// Where an integrator takes its numbers from: one sample's [`Sampler`], or one lane of a
/// [`SampleWave`], which gives the same numbers.
pub trait Draws {
    /// See [`Sampler::start_bounce`].
    fn start_bounce(&mut self, bounce: u32);
    /// See [`Sampler::get_1d`].
    fn get_1d(&mut self) -> f32;
    /// See [`Sampler::get_2d`].
    fn get_2d(&mut self) -> (f32, f32);
    /// See [`Sampler::get_2d_after`].
    fn get_2d_after(&mut self, first: u32) -> (f32, f32);
    /// See [`Sampler::dim`].
    fn dim(&self) -> u32;
    /// See [`Sampler::key`].
    fn key(&self) -> SampleKey;
}

impl Draws for Sampler<'_> {
    #[inline(always)]
    fn start_bounce(&mut self, bounce: u32) {
        Sampler::start_bounce(self, bounce)
    }
    #[inline(always)]
    fn get_1d(&mut self) -> f32 {
        Sampler::get_1d(self)
    }
    #[inline(always)]
    fn get_2d(&mut self) -> (f32, f32) {
        Sampler::get_2d(self)
    }
    #[inline(always)]
    fn get_2d_after(&mut self, first: u32) -> (f32, f32) {
        Sampler::get_2d_after(self, first)
    }
    #[inline(always)]
    fn dim(&self) -> u32 {
        Sampler::dim(self)
    }
    #[inline(always)]
    fn key(&self) -> SampleKey {
        Sampler::key(self)
    }
}

/// Samples a wave holds at most: eight lanes of 32 bits, one AVX2 register.
pub const WAVE_LANES: u32 = 8;

/// Up to eight consecutive samples of one pixel whose paths take their bounces in step: the
/// numbers of each bounce are drawn for all of them at once, eight lanes at a time, before
/// the paths take it. Their seeds are the pixel's (the same in every lane), only the sample
/// index differs, so a draw is the scalar one's operations on eight indices: the hashes of
/// a path's numbers, a tenth of its instructions when drawn one by one, cost a few
/// instructions a sample. A lane gives exactly the numbers of its sample's [`Sampler`]
/// ([`WaveLane`]), so an image does not depend on which way its pixels were sampled.
pub struct SampleWave<'a> {
    seeds: &'a PixelSeeds,
    first: u32,
    /// Bit-reversed sample index of each lane.
    reversed: [u32; 8],
    /// The dimension of the last direction draw (the pixel position's, before the first
    /// bounce), which the next light draw continues, and its shuffled indices.
    after: u32,
    after_index: U32x8,
    /// The first dimension of a bounce whose numbers are to be drawn when a lane first asks
    /// for one of them: a path that leaves the scene asks for none.
    wanted: Option<u32>,
    /// Whether a bounce's numbers are held, and the first dimension of that bounce.
    held: bool,
    base: u32,
    /// At `base`: the light draw continuing the direction draw at `light_after`.
    light_after: u32,
    light: [[f32; 8]; 2],
    /// At `base + 1`: the direction draw.
    direction: [[f32; 8]; 2],
    /// At `base + 2` and `base + 3`: one number each (the lobe, Russian roulette).
    single: [[f32; 8]; 2],
}

impl<'a> SampleWave<'a> {
    /// Samples `first..first + 8` of the pixel of `seeds` (lanes past the pixel's last
    /// sample are drawn for and never used).
    pub fn new(seeds: &'a PixelSeeds, first: u32) -> SampleWave<'a> {
        let index: [u32; 8] = std::array::from_fn(|i| first.wrapping_add(i as u32));
        let mut reversed = [0; 8];
        U32x8::load(&index).reverse_bits().store(&mut reversed);
        SampleWave {
            seeds,
            first,
            reversed,
            after: PIXEL_DIM,
            after_index: U32x8::splat(0),
            wanted: None,
            held: false,
            base: 0,
            light_after: PIXEL_DIM,
            light: [[0.0; 8]; 2],
            direction: [[0.0; 8]; 2],
            single: [[0.0; 8]; 2],
        }
    }

    #[inline(always)]
    fn seeds_of(&self, dim: u32) -> DimSeeds {
        kept_seeds(&self.seeds.dims, self.seeds.pixel, dim)
    }

    /// Each lane's index in dimension `dim`'s order ([`Sampler::shuffled`]).
    #[inline(always)]
    fn shuffled(&self, shuffle: u32) -> U32x8 {
        laine_karras8(U32x8::load(&self.reversed), shuffle).reverse_bits()
    }

    /// [`Sampler::get_2d`] at `dim` in every lane, and the shuffled indices it used.
    #[inline(always)]
    fn draw_2d(&self, dim: u32) -> ([[f32; 8]; 2], U32x8) {
        let [shuffle, sx, sy, _] = self.seeds_of(dim);
        let index = self.shuffled(shuffle);
        let x = laine_karras8(index, sx).reverse_bits();
        let y = laine_karras8(sobol_reversed8(&SOBOL_SECOND_REVERSED, index), sy).reverse_bits();
        ([x.unit(), y.unit()], index)
    }

    /// [`Sampler::get_1d`] at `dim` in every lane.
    #[inline(always)]
    fn draw_1d(&self, dim: u32) -> [f32; 8] {
        let [shuffle, sx, _, _] = self.seeds_of(dim);
        laine_karras8(self.shuffled(shuffle), sx)
            .reverse_bits()
            .unit()
    }

    /// Each lane's position within the pixel ([`Sampler::pixel_2d`]).
    pub fn pixel_2d(&mut self) -> [(f32, f32); 8] {
        let ([x, y], index) = self.draw_2d(PIXEL_DIM);
        self.after = PIXEL_DIM;
        self.after_index = index;
        std::array::from_fn(|i| (x[i], y[i]))
    }

    /// The numbers of bounce `bounce` are to be drawn for every lane, once a lane asks for
    /// one of them. Called once per bounce, in order, after [`SampleWave::pixel_2d`]: each
    /// light draw continues the direction draw of the bounce before, and a bounce that some
    /// path goes on from was drawn (its path asked for its direction).
    pub fn want_bounce(&mut self, bounce: u32) {
        self.wanted = Some(bounce_dim(bounce));
    }

    /// Draws the numbers of bounce `bounce` for every lane (see [`SampleWave::want_bounce`]).
    pub fn draw_bounce(&mut self, bounce: u32) {
        self.draw_at(bounce_dim(bounce));
    }

    /// [`SampleWave::draw_bounce`] for the bounce whose first dimension is `base`.
    fn draw_at(&mut self, base: u32) {
        self.wanted = None;
        if self.held && base == self.base {
            return;
        }
        let [_, sx, sy, _] = self.seeds_of(base);
        let index = self.after_index;
        let x = laine_karras8(sobol_reversed8(&SOBOL_THIRD_REVERSED, index), sx).reverse_bits();
        let y = laine_karras8(sobol_reversed8(&SOBOL_FOURTH_REVERSED, index), sy).reverse_bits();
        self.light = [x.unit(), y.unit()];
        let (direction, index) = self.draw_2d(base.wrapping_add(1));
        self.direction = direction;
        self.single = [
            self.draw_1d(base.wrapping_add(2)),
            self.draw_1d(base.wrapping_add(3)),
        ];
        // The light draw at this base continues `after`; the next one continues this
        // bounce's direction draw.
        self.held = true;
        self.base = base;
        self.light_after = self.after;
        self.after = base.wrapping_add(1);
        self.after_index = index;
    }

    /// Holds no numbers any more: each lane draws its own from here on.
    pub fn release(&mut self) {
        self.held = false;
        self.wanted = None;
    }

    /// Lane `lane`'s numbers: sample `first + lane`.
    pub fn lane(&mut self, lane: usize) -> WaveLane<'_, 'a> {
        let seeds: &'a PixelSeeds = self.seeds;
        let sampler =
            seeds.sampler_reversed(self.first.wrapping_add(lane as u32), self.reversed[lane]);
        WaveLane {
            wave: self,
            lane,
            sampler,
        }
    }
}

/// One sample of a [`SampleWave`]: its numbers, taken from what the wave drew where they are
/// there, drawn on their own otherwise; the same numbers either way.
pub struct WaveLane<'w, 'a> {
    wave: &'w mut SampleWave<'a>,
    lane: usize,
    sampler: Sampler<'a>,
}

impl WaveLane<'_, '_> {
    /// Which of the held draws the next draw is: its offset from the held bounce's first
    /// dimension, when the wave holds numbers (drawn now, if they are wanted and not drawn).
    #[inline(always)]
    fn held_offset(&mut self) -> Option<u32> {
        let w = &mut *self.wave;
        if let Some(base) = w.wanted
            && self.sampler.dim.wrapping_sub(base) < 4
        {
            w.draw_at(base);
        }
        let k = self.sampler.dim.wrapping_sub(w.base);
        (w.held && k < 4).then_some(k)
    }

    #[inline(always)]
    fn take(&mut self) {
        self.sampler.dim = self.sampler.dim.wrapping_add(1);
    }
}

impl Draws for WaveLane<'_, '_> {
    #[inline(always)]
    fn start_bounce(&mut self, bounce: u32) {
        self.sampler.start_bounce(bounce)
    }
    #[inline(always)]
    fn get_1d(&mut self) -> f32 {
        match self.held_offset() {
            Some(k @ 2..=3) => {
                self.take();
                self.wave.single[k as usize - 2][self.lane]
            }
            _ => self.sampler.get_1d(),
        }
    }
    #[inline(always)]
    fn get_2d(&mut self) -> (f32, f32) {
        match self.held_offset() {
            Some(1) => {
                self.take();
                let d = &self.wave.direction;
                (d[0][self.lane], d[1][self.lane])
            }
            _ => self.sampler.get_2d(),
        }
    }
    #[inline(always)]
    fn get_2d_after(&mut self, first: u32) -> (f32, f32) {
        match self.held_offset() {
            Some(0) if first == self.wave.light_after => {
                self.take();
                let l = &self.wave.light;
                (l[0][self.lane], l[1][self.lane])
            }
            _ => self.sampler.get_2d_after(first),
        }
    }
    #[inline(always)]
    fn dim(&self) -> u32 {
        self.sampler.dim
    }
    #[inline(always)]
    fn key(&self) -> SampleKey {
        self.sampler.key()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The draws of one bounce as the path tracer makes them (a lobe draw or not), then
    /// draws the wave does not hold (past the bounce's four, and a light draw continuing
    /// another dimension), as bits.
    fn bounce_draws(s: &mut impl Draws, bounce: u32, first: u32, lobe: bool) -> Vec<u32> {
        let mut out = Vec::new();
        let two = |(a, b): (f32, f32)| [a.to_bits(), b.to_bits()];
        s.start_bounce(bounce);
        out.extend(two(s.get_2d_after(first)));
        out.push(s.dim());
        out.extend(two(s.get_2d()));
        if lobe {
            out.push(s.get_1d().to_bits());
        }
        out.push(s.get_1d().to_bits());
        out.push(s.get_1d().to_bits());
        out.extend(two(s.get_2d()));
        s.start_bounce(bounce);
        out.extend(two(s.get_2d_after(first ^ 1)));
        out.push(s.dim());
        out
    }

    /// Each lane of a wave gives its sample's numbers, bit for bit, whether the wave holds
    /// them or not.
    #[test]
    fn a_wave_lane_draws_the_numbers_of_its_sample() {
        for (seed, px, py, first) in [
            (0u64, 0u32, 0u32, 0u32),
            (5, 3, 4, 8),
            (77, 1000, 3, 1016),
            (1, 2, 3, u32::MAX - 3),
        ] {
            let seeds = PixelSeeds::new(seed, px, py);
            let mut wave = SampleWave::new(&seeds, first);
            let pixel = wave.pixel_2d();
            for (lane, &(x, y)) in pixel.iter().enumerate() {
                let mut s = Sampler::new(seed, px, py, first.wrapping_add(lane as u32));
                let (wx, wy) = s.pixel_2d();
                assert_eq!((x.to_bits(), y.to_bits()), (wx.to_bits(), wy.to_bits()));
            }
            let mut first_dim = PIXEL_DIM;
            for bounce in 0..12 {
                if bounce % 2 == 0 {
                    wave.draw_bounce(bounce);
                    // Drawn twice: the second call keeps what the first drew.
                    wave.draw_bounce(bounce);
                } else {
                    // Drawn when the first lane asks.
                    wave.want_bounce(bounce);
                }
                for lane in 0..WAVE_LANES as usize {
                    let sample = first.wrapping_add(lane as u32);
                    let lobe = (lane + bounce as usize).is_multiple_of(3);
                    let want = bounce_draws(
                        &mut Sampler::new(seed, px, py, sample),
                        bounce,
                        first_dim,
                        lobe,
                    );
                    let got = bounce_draws(&mut wave.lane(lane), bounce, first_dim, lobe);
                    assert_eq!(got, want, "seed {seed} sample {sample} bounce {bounce}");
                    // What the wave holds is what the lanes were given (the test above
                    // would pass as well if every draw were made on its own).
                    let held = [
                        wave.light[0][lane],
                        wave.light[1][lane],
                        wave.direction[0][lane],
                        wave.direction[1][lane],
                        wave.single[0][lane],
                        wave.single[1][lane],
                    ]
                    .map(f32::to_bits);
                    let alone = {
                        let mut s = Sampler::new(seed, px, py, sample);
                        s.start_bounce(bounce);
                        let l = s.get_2d_after(first_dim);
                        let d = s.get_2d();
                        [l.0, l.1, d.0, d.1, s.get_1d(), s.get_1d()].map(f32::to_bits)
                    };
                    assert_eq!(held, alone, "seed {seed} sample {sample} bounce {bounce}");
                }
                first_dim = bounce_dim(bounce) + 1;
            }
        }
    }

    /// Owen scrambling of a fraction given as 32 bits, most significant first.
    fn owen(x: u32, seed: u32) -> u32 {
        reverse(laine_karras(reverse(x), seed))
    }

    /// The tables and folded reversals give the textbook construction's numbers.
    #[test]
    fn draws_are_owen_scrambled_sobol_points() {
        fn sobol_second(mut index: u32) -> u32 {
            let (mut v, mut x) = (1u32 << 31, 0);
            while index != 0 {
                if index & 1 != 0 {
                    x ^= v;
                }
                index >>= 1;
                v ^= v >> 1;
            }
            x
        }
        for sample in [0u32, 1, 2, 3, 77, 1023, 65_537, u32::MAX] {
            let mut s = Sampler::new(5, 3, 4, sample);
            s.dim = 9;
            let (shuffle, sx, sy) = {
                let mut copy = s;
                copy.seeds()
            };
            let index = owen(sample, shuffle);
            let want = (
                unit(owen(reverse(index), sx)),
                unit(owen(sobol_second(index), sy)),
            );
            assert_eq!(s.get_2d(), want, "sample {sample}");
        }
    }

    /// A draw after another takes that draw's shuffled index at the Sobol sequence's third
    /// and fourth dimensions, as the textbook recurrence on Joe and Kuo's direction numbers
    /// gives them (m_k = 2 m_{k-1} ^ 4 m_{k-2} ^ m_{k-2} for x^2 + x + 1 from 1, 3;
    /// m_k = 4 m_{k-2} ^ 8 m_{k-3} ^ m_{k-3} for x^3 + x + 1 from 1, 3, 1).
    #[test]
    fn draws_after_are_the_third_and_fourth_sobol_dimensions() {
        fn point(m: &[u64], mut index: u32) -> u32 {
            let mut x = 0u32;
            let mut k = 0;
            while index != 0 {
                if index & 1 != 0 {
                    x ^= (m[k] << (31 - k)) as u32;
                }
                index >>= 1;
                k += 1;
            }
            x
        }
        let (mut third, mut fourth) = (vec![1u64, 3], vec![1u64, 3, 1]);
        for k in 2..32 {
            third.push((2 * third[k - 1]) ^ (4 * third[k - 2]) ^ third[k - 2]);
        }
        for k in 3..32 {
            fourth.push((4 * fourth[k - 2]) ^ (8 * fourth[k - 3]) ^ fourth[k - 3]);
        }
        assert_eq!(&third[..5], &[1, 3, 3, 9, 29]);
        for sample in [0u32, 1, 2, 3, 77, 1023, 65_537, u32::MAX] {
            let mut s = Sampler::new(5, 3, 4, sample);
            s.dim = 9;
            let (shuffle, _, _) = s.seeds();
            s.dim = 14;
            let (_, sx, sy) = {
                let mut copy = s;
                copy.seeds()
            };
            let index = owen(sample, shuffle);
            let want = (
                unit(owen(point(&third, index), sx)),
                unit(owen(point(&fourth, index), sy)),
            );
            assert_eq!(s.get_2d_after(9), want, "sample {sample}");
        }
    }

    /// The first 2^k draws after another put one number in each 2^-k interval, in both
    /// coordinates, whatever the first draw's dimension.
    #[test]
    fn draws_after_are_stratified_in_each_coordinate() {
        for (first, dim) in [(0u32, 4u32), (5, 21), (37, 52)] {
            for k in [4u32, 8] {
                let n = 1u32 << k;
                let (mut xs, mut ys) = (vec![false; n as usize], vec![false; n as usize]);
                for i in 0..n {
                    let mut s = Sampler::new(3, 17, 9, i);
                    s.dim = dim;
                    let (x, y) = s.get_2d_after(first);
                    for (seen, v) in [(&mut xs, x), (&mut ys, y)] {
                        let cell = (v * n as f32) as usize;
                        assert!(!seen[cell], "first {first}, dim {dim}, {n} samples");
                        seen[cell] = true;
                    }
                }
            }
        }
    }

    /// A pixel's kept seeds give the numbers of samplers made on their own, whichever
    /// sample draws a dimension first, past the kept dimensions too.
    #[test]
    fn kept_seeds_change_no_number() {
        let seeds = PixelSeeds::new(9, 31, 7);
        for sample in [5u32, 0, 5, 1000, 3] {
            let mut kept = seeds.sampler(sample);
            let mut alone = Sampler::new(9, 31, 7, sample);
            assert_eq!(kept.pixel_2d(), alone.pixel_2d());
            for bounce in [0u32, 1, 7, 8, 12, 63] {
                kept.start_bounce(bounce);
                alone.start_bounce(bounce);
                assert_eq!(
                    kept.get_2d(),
                    alone.get_2d(),
                    "sample {sample} bounce {bounce}"
                );
                assert_eq!(
                    kept.get_1d(),
                    alone.get_1d(),
                    "sample {sample} bounce {bounce}"
                );
            }
            assert_eq!(kept.keyed(2, 3, 4), alone.keyed(2, 3, 4));
        }
    }

    #[test]
    fn a_pair_reversal_is_two_reversals() {
        for (a, b) in [
            (0u32, 0u32),
            (1, 2),
            (0x8000_0001, 0xdead_beef),
            (u32::MAX, 7),
        ] {
            assert_eq!(reverse_pair(a, b), (reverse(a), reverse(b)));
        }
    }

    #[test]
    fn same_key_same_numbers() {
        let mut a = Sampler::new(7, 10, 20, 3);
        let mut b = Sampler::new(7, 10, 20, 3);
        a.start_bounce(2);
        b.start_bounce(2);
        assert_eq!(a.get_2d(), b.get_2d());
        assert_eq!(a.get_1d(), b.get_1d());
    }

    /// The first 2^k samples of a pixel put exactly one point in each of the 2^k cells of
    /// every elementary grid (a (0, m, 2)-net): what makes them better than random ones.
    #[test]
    fn each_pixel_s_samples_are_stratified_in_2d() {
        for (px, dim) in [(0u32, 0u32), (5, 4), (77, 20), (1234, 37)] {
            for k in [4u32, 6, 8] {
                let n = 1u32 << k;
                for split in 0..=k {
                    let (cols, rows) = (1u32 << split, 1u32 << (k - split));
                    let mut seen = vec![false; n as usize];
                    for i in 0..n {
                        let mut s = Sampler::new(3, px, 9, i);
                        s.dim = dim;
                        let (x, y) = s.get_2d();
                        let cell = (y * rows as f32) as u32 * cols + (x * cols as f32) as u32;
                        assert!(
                            !seen[cell as usize],
                            "pixel {px}, dim {dim}, {n} samples, {cols}x{rows}"
                        );
                        seen[cell as usize] = true;
                    }
                }
            }
        }
    }

    #[test]
    fn dimensions_and_pixels_are_uncorrelated() {
        // The same sample in neighbouring pixels, or two dimensions of one sample, must not
        // give related numbers (a shared scramble would make them equal).
        let n = 4096;
        let mut same = 0;
        for i in 0..n {
            let mut a = Sampler::new(1, i, 0, 7);
            let mut b = Sampler::new(1, i + 1, 0, 7);
            let (x0, y0) = a.get_2d();
            let (x1, _) = b.get_2d();
            let (x2, _) = a.get_2d();
            same += ((x0 * 8.0) as u32 == (x1 * 8.0) as u32) as u32;
            same += ((x0 * 8.0) as u32 == (x2 * 8.0) as u32) as u32;
            same += ((x0 * 8.0) as u32 == (y0 * 8.0) as u32) as u32;
        }
        // Independent: each pair lands in the same eighth with probability 1/8.
        let expected = 3.0 * n as f64 / 8.0;
        assert!(
            (same as f64 - expected).abs() < 0.1 * expected,
            "{same} vs {expected}"
        );
    }

    #[test]
    fn uniform_mean_and_range() {
        let mut sum = 0.0f64;
        let n = 100_000;
        for i in 0..n {
            let mut s = Sampler::new(1, i % 317, i / 317, i);
            s.start_bounce(0);
            let v = s.get_1d();
            assert!((0.0..1.0).contains(&v));
            sum += v as f64;
        }
        assert!((sum / n as f64 - 0.5).abs() < 0.005);
    }
}
