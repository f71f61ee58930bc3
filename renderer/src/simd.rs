//! Small SIMD types: eight and four `f32` lanes and their masks for the ray-casting kernel
//! and the shading of a wave's diffuse hits, eight `u32` lanes for the sampler's hashes.
//!
//! With AVX2 and FMA (the default build, x86-64-v3) each operation is one instruction; on
//! other targets the same operations run lane by lane. Both give the same bits: `min`/`max`
//! follow the SSE rule (`a < b ? a : b`, which also fixes which operand a NaN yields), and
//! `mul_add` is fused in both (`f32::mul_add` is correctly rounded, like the instruction).
//! The kernel is written once against these types.
//!
//! Some operations read a lane's bits as a signed integer (`max_bits`, `min_bits`,
//! `below_bits`): floats not negative order as their bit patterns do, and every negative
//! float (-0.0 among them) is a negative integer, below all of them. Where an answer is known
//! not to be negative, these give the float answer, one cycle each instead of four.

#![allow(clippy::should_implement_trait)]

#[cfg(all(
    target_arch = "x86_64",
    target_feature = "avx2",
    target_feature = "fma"
))]
mod imp {
    use std::arch::x86_64::*;

    /// Eight `f32` lanes.
    #[derive(Clone, Copy, Debug)]
    #[repr(transparent)]
    pub struct F32x8(__m256);

    /// Four `f32` lanes.
    #[derive(Clone, Copy, Debug)]
    #[repr(transparent)]
    pub struct F32x4(__m128);

    /// A lane mask of [`F32x8`] comparisons (all bits set where true).
    #[derive(Clone, Copy, Debug)]
    #[repr(transparent)]
    pub struct M8(__m256);

    /// A lane mask of [`F32x4`] comparisons.
    #[derive(Clone, Copy, Debug)]
    #[repr(transparent)]
    pub struct M4(__m128);

    // SAFETY (every block below): this module is compiled only when the target has AVX2 and
    // FMA (checked by the binaries at start, see `magg::cpu`), and loads take references to
    // arrays of exactly the width read.
    impl F32x8 {
        #[inline(always)]
        pub fn load(a: &[f32; 8]) -> F32x8 {
            unsafe { F32x8(_mm256_loadu_ps(a.as_ptr())) }
        }
        #[inline(always)]
        pub fn splat(x: f32) -> F32x8 {
            unsafe { F32x8(_mm256_set1_ps(x)) }
        }
        #[inline(always)]
        pub fn store(self, out: &mut [f32; 8]) {
            unsafe { _mm256_storeu_ps(out.as_mut_ptr(), self.0) }
        }
        /// `self * b + c`, rounded once.
        #[inline(always)]
        pub fn mul_add(self, b: F32x8, c: F32x8) -> F32x8 {
            unsafe { F32x8(_mm256_fmadd_ps(self.0, b.0, c.0)) }
        }
        #[inline(always)]
        pub fn mul(self, b: F32x8) -> F32x8 {
            unsafe { F32x8(_mm256_mul_ps(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn min(self, b: F32x8) -> F32x8 {
            unsafe { F32x8(_mm256_min_ps(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn max(self, b: F32x8) -> F32x8 {
            unsafe { F32x8(_mm256_max_ps(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn le(self, b: F32x8) -> M8 {
            unsafe { M8(_mm256_cmp_ps::<_CMP_LE_OQ>(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn lt(self, b: F32x8) -> M8 {
            unsafe { M8(_mm256_cmp_ps::<_CMP_LT_OQ>(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn gt(self, b: F32x8) -> M8 {
            unsafe { M8(_mm256_cmp_ps::<_CMP_GT_OQ>(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn eq(self, b: F32x8) -> M8 {
            unsafe { M8(_mm256_cmp_ps::<_CMP_EQ_OQ>(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn add(self, b: F32x8) -> F32x8 {
            unsafe { F32x8(_mm256_add_ps(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn sub(self, b: F32x8) -> F32x8 {
            unsafe { F32x8(_mm256_sub_ps(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn div(self, b: F32x8) -> F32x8 {
            unsafe { F32x8(_mm256_div_ps(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn sqrt(self) -> F32x8 {
            unsafe { F32x8(_mm256_sqrt_ps(self.0)) }
        }
        #[inline(always)]
        pub fn abs(self) -> F32x8 {
            unsafe { F32x8(_mm256_andnot_ps(_mm256_set1_ps(-0.0), self.0)) }
        }
        /// The lanes with their sign bit flipped (`-x`, NaNs included).
        #[inline(always)]
        pub fn neg(self) -> F32x8 {
            unsafe { F32x8(_mm256_xor_ps(self.0, _mm256_set1_ps(-0.0))) }
        }
        /// `1.0f32.copysign(x)` of each lane.
        #[inline(always)]
        pub fn one_with_sign_of(self) -> F32x8 {
            unsafe {
                let sign = _mm256_and_ps(self.0, _mm256_set1_ps(-0.0));
                F32x8(_mm256_or_ps(sign, _mm256_set1_ps(1.0)))
            }
        }
        /// Lanes neither infinite nor NaN.
        #[inline(always)]
        pub fn is_finite(self) -> M8 {
            self.abs().lt(F32x8::splat(f32::INFINITY))
        }
        /// The larger bit pattern of each lane pair, compared as signed integers (see
        /// [`crate::simd`]: the float maximum wherever it is not negative).
        #[inline(always)]
        pub fn max_bits(self, b: F32x8) -> F32x8 {
            unsafe {
                let m = _mm256_max_epi32(_mm256_castps_si256(self.0), _mm256_castps_si256(b.0));
                F32x8(_mm256_castsi256_ps(m))
            }
        }
        /// The smaller bit pattern of each lane pair, compared as signed integers (the
        /// float minimum where both are not negative, a negative number where one is).
        #[inline(always)]
        pub fn min_bits(self, b: F32x8) -> F32x8 {
            unsafe {
                let m = _mm256_min_epi32(_mm256_castps_si256(self.0), _mm256_castps_si256(b.0));
                F32x8(_mm256_castsi256_ps(m))
            }
        }
        /// Each lane's bit pattern less `ulps`, as a signed integer: a distance that is not
        /// negative moved `ulps` units in the last place down (below zero, a negative integer,
        /// which [`F32x8::below_bits`] finds below every distance that is not negative).
        #[inline(always)]
        pub fn less_ulps(self, ulps: i32) -> F32x8 {
            unsafe {
                let d = _mm256_sub_epi32(_mm256_castps_si256(self.0), _mm256_set1_epi32(ulps));
                F32x8(_mm256_castsi256_ps(d))
            }
        }
        /// Lanes whose bit pattern is below `b`'s, as signed integers (see [`crate::simd`]:
        /// `self < b` where `self` is not negative; never where `b` is negative).
        #[inline(always)]
        pub fn below_bits(self, b: F32x8) -> M8 {
            unsafe {
                M8(_mm256_castsi256_ps(_mm256_cmpgt_epi32(
                    _mm256_castps_si256(b.0),
                    _mm256_castps_si256(self.0),
                )))
            }
        }
        /// Lanes 0 to 3 from `lo`, 4 to 7 from `hi`.
        #[inline(always)]
        pub fn load_halves(lo: &[f32; 4], hi: &[f32; 4]) -> F32x8 {
            unsafe { F32x8(_mm256_loadu2_m128(hi.as_ptr(), lo.as_ptr())) }
        }
        #[inline(always)]
        pub fn zero() -> F32x8 {
            unsafe { F32x8(_mm256_setzero_ps()) }
        }
        /// `c - self * b`, rounded once.
        #[inline(always)]
        pub fn neg_mul_add(self, b: F32x8, c: F32x8) -> F32x8 {
            unsafe { F32x8(_mm256_fnmadd_ps(self.0, b.0, c.0)) }
        }
        /// As [`F32x4::signs_differ`].
        #[inline(always)]
        pub fn signs_differ(self, b: F32x8, c: F32x8) -> u32 {
            unsafe {
                let d = _mm256_or_ps(_mm256_xor_ps(self.0, b.0), _mm256_xor_ps(self.0, c.0));
                _mm256_movemask_ps(d) as u32
            }
        }
        /// The lanes with their sign bit flipped where `sign` has it set.
        #[inline(always)]
        pub fn xor_sign(self, sign: F32x8) -> F32x8 {
            unsafe {
                let bit = _mm256_and_ps(sign.0, _mm256_set1_ps(-0.0));
                F32x8(_mm256_xor_ps(self.0, bit))
            }
        }
        #[inline(always)]
        pub fn ne(self, b: F32x8) -> M8 {
            unsafe { M8(_mm256_cmp_ps::<_CMP_NEQ_UQ>(self.0, b.0)) }
        }
    }

    impl M8 {
        /// Bit i set when lane i is true.
        #[inline(always)]
        pub fn bits(self) -> u32 {
            unsafe { _mm256_movemask_ps(self.0) as u32 }
        }
        #[inline(always)]
        pub fn and(self, b: M8) -> M8 {
            unsafe { M8(_mm256_and_ps(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn or(self, b: M8) -> M8 {
            unsafe { M8(_mm256_or_ps(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn not(self) -> M8 {
            unsafe {
                M8(_mm256_xor_ps(
                    self.0,
                    _mm256_castsi256_ps(_mm256_set1_epi32(-1)),
                ))
            }
        }
        /// `a` where the mask is true, `b` elsewhere.
        #[inline(always)]
        pub fn select(self, a: F32x8, b: F32x8) -> F32x8 {
            unsafe { F32x8(_mm256_blendv_ps(b.0, a.0, self.0)) }
        }
    }

    impl F32x4 {
        #[inline(always)]
        pub fn load(a: &[f32; 4]) -> F32x4 {
            unsafe { F32x4(_mm_loadu_ps(a.as_ptr())) }
        }
        #[inline(always)]
        pub fn splat(x: f32) -> F32x4 {
            unsafe { F32x4(_mm_set1_ps(x)) }
        }
        #[inline(always)]
        pub fn zero() -> F32x4 {
            unsafe { F32x4(_mm_setzero_ps()) }
        }
        #[inline(always)]
        pub fn store(self, out: &mut [f32; 4]) {
            unsafe { _mm_storeu_ps(out.as_mut_ptr(), self.0) }
        }
        #[inline(always)]
        pub fn add(self, b: F32x4) -> F32x4 {
            unsafe { F32x4(_mm_add_ps(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn sub(self, b: F32x4) -> F32x4 {
            unsafe { F32x4(_mm_sub_ps(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn mul(self, b: F32x4) -> F32x4 {
            unsafe { F32x4(_mm_mul_ps(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn div(self, b: F32x4) -> F32x4 {
            unsafe { F32x4(_mm_div_ps(self.0, b.0)) }
        }
        /// `self * b + c`, rounded once.
        #[inline(always)]
        pub fn mul_add(self, b: F32x4, c: F32x4) -> F32x4 {
            unsafe { F32x4(_mm_fmadd_ps(self.0, b.0, c.0)) }
        }
        /// `c - self * b`, rounded once.
        #[inline(always)]
        pub fn neg_mul_add(self, b: F32x4, c: F32x4) -> F32x4 {
            unsafe { F32x4(_mm_fnmadd_ps(self.0, b.0, c.0)) }
        }
        /// Bit i set when lanes i of `self`, `b` and `c` do not all have the same sign bit
        /// (zeros and NaNs count by their sign bit, as they are).
        #[inline(always)]
        pub fn signs_differ(self, b: F32x4, c: F32x4) -> u32 {
            unsafe {
                let d = _mm_or_ps(_mm_xor_ps(self.0, b.0), _mm_xor_ps(self.0, c.0));
                _mm_movemask_ps(d) as u32
            }
        }
        /// The lanes with their sign bit flipped where `sign` has it set.
        #[inline(always)]
        pub fn xor_sign(self, sign: F32x4) -> F32x4 {
            unsafe {
                let bit = _mm_and_ps(sign.0, _mm_set1_ps(-0.0));
                F32x4(_mm_xor_ps(self.0, bit))
            }
        }
        #[inline(always)]
        pub fn abs(self) -> F32x4 {
            unsafe { F32x4(_mm_andnot_ps(_mm_set1_ps(-0.0), self.0)) }
        }
        #[inline(always)]
        pub fn max(self, b: F32x4) -> F32x4 {
            unsafe { F32x4(_mm_max_ps(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn lt(self, b: F32x4) -> M4 {
            unsafe { M4(_mm_cmp_ps::<_CMP_LT_OQ>(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn gt(self, b: F32x4) -> M4 {
            unsafe { M4(_mm_cmp_ps::<_CMP_GT_OQ>(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn eq(self, b: F32x4) -> M4 {
            unsafe { M4(_mm_cmp_ps::<_CMP_EQ_OQ>(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn ne(self, b: F32x4) -> M4 {
            unsafe { M4(_mm_cmp_ps::<_CMP_NEQ_UQ>(self.0, b.0)) }
        }
    }

    impl M4 {
        #[inline(always)]
        pub fn bits(self) -> u32 {
            unsafe { _mm_movemask_ps(self.0) as u32 }
        }
        #[inline(always)]
        pub fn and(self, b: M4) -> M4 {
            unsafe { M4(_mm_and_ps(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn or(self, b: M4) -> M4 {
            unsafe { M4(_mm_or_ps(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn not(self) -> M4 {
            unsafe { M4(_mm_xor_ps(self.0, _mm_castsi128_ps(_mm_set1_epi32(-1)))) }
        }
    }

    /// Eight `u32` lanes, with wrapping arithmetic.
    #[derive(Clone, Copy, Debug)]
    #[repr(transparent)]
    pub struct U32x8(__m256i);

    /// What a shuffle table holds at byte `i` of each 128-bit half.
    #[derive(Clone, Copy)]
    enum Shuffle {
        /// The nibble `i` reversed, in the high half of the byte.
        NibbleReversedHigh,
        /// The nibble `i` reversed.
        NibbleReversed,
        /// Byte order within each 32-bit lane reversed.
        BytesReversed,
    }

    const fn shuffle_table(kind: Shuffle) -> [u8; 32] {
        let mut t = [0u8; 32];
        let mut i = 0;
        while i < 32 {
            let j = i as u8 & 15;
            t[i] = match kind {
                Shuffle::NibbleReversedHigh => j.reverse_bits(),
                Shuffle::NibbleReversed => j.reverse_bits() >> 4,
                Shuffle::BytesReversed => (j & !3) + 3 - (j & 3),
            };
            i += 1;
        }
        t
    }
    const NIBBLE_REVERSED_HIGH: [u8; 32] = shuffle_table(Shuffle::NibbleReversedHigh);
    const NIBBLE_REVERSED: [u8; 32] = shuffle_table(Shuffle::NibbleReversed);
    const BYTES_REVERSED: [u8; 32] = shuffle_table(Shuffle::BytesReversed);

    impl U32x8 {
        #[inline(always)]
        pub fn load(a: &[u32; 8]) -> U32x8 {
            unsafe { U32x8(_mm256_loadu_si256(a.as_ptr().cast())) }
        }
        #[inline(always)]
        pub fn splat(x: u32) -> U32x8 {
            unsafe { U32x8(_mm256_set1_epi32(x as i32)) }
        }
        #[inline(always)]
        pub fn store(self, out: &mut [u32; 8]) {
            unsafe { _mm256_storeu_si256(out.as_mut_ptr().cast(), self.0) }
        }
        #[inline(always)]
        pub fn wrapping_add(self, b: U32x8) -> U32x8 {
            unsafe { U32x8(_mm256_add_epi32(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn wrapping_mul(self, b: U32x8) -> U32x8 {
            unsafe { U32x8(_mm256_mullo_epi32(self.0, b.0)) }
        }
        #[inline(always)]
        pub fn xor(self, b: U32x8) -> U32x8 {
            unsafe { U32x8(_mm256_xor_si256(self.0, b.0)) }
        }
        /// Each lane shifted right by `N` bits.
        #[inline(always)]
        pub fn shr<const N: i32>(self) -> U32x8 {
            unsafe { U32x8(_mm256_srli_epi32::<N>(self.0)) }
        }
        /// Each lane's bits in reverse order: its bytes reversed with one shuffle, then each
        /// byte's two nibbles reversed and swapped by two table shuffles.
        #[inline(always)]
        pub fn reverse_bits(self) -> U32x8 {
            unsafe {
                let load = |t: &[u8; 32]| _mm256_loadu_si256(t.as_ptr().cast());
                let x = _mm256_shuffle_epi8(self.0, load(&BYTES_REVERSED));
                let nibble = _mm256_set1_epi8(15);
                let low = _mm256_and_si256(x, nibble);
                let high = _mm256_and_si256(_mm256_srli_epi16::<4>(x), nibble);
                U32x8(_mm256_or_si256(
                    _mm256_shuffle_epi8(load(&NIBBLE_REVERSED_HIGH), low),
                    _mm256_shuffle_epi8(load(&NIBBLE_REVERSED), high),
                ))
            }
        }
        /// `table[lane & 255]` for each lane.
        #[inline(always)]
        pub fn lookup(self, table: &[u32; 256]) -> U32x8 {
            unsafe {
                let i = _mm256_and_si256(self.0, _mm256_set1_epi32(255));
                U32x8(_mm256_i32gather_epi32::<4>(table.as_ptr().cast(), i))
            }
        }
        /// The top 24 bits of each lane as a fraction in [0, 1): `(x >> 8) as f32 * 2^-24`.
        #[inline(always)]
        pub fn unit(self) -> [f32; 8] {
            let mut out = [0.0; 8];
            unsafe {
                let f = _mm256_cvtepi32_ps(_mm256_srli_epi32::<8>(self.0));
                _mm256_storeu_ps(
                    out.as_mut_ptr(),
                    _mm256_mul_ps(f, _mm256_set1_ps(1.0 / (1u32 << 24) as f32)),
                );
            }
            out
        }
    }
}

#[cfg(not(all(
    target_arch = "x86_64",
    target_feature = "avx2",
    target_feature = "fma"
)))]
mod imp {
    /// Eight `f32` lanes.
    #[derive(Clone, Copy, Debug)]
    pub struct F32x8([f32; 8]);

    /// Four `f32` lanes.
    #[derive(Clone, Copy, Debug)]
    pub struct F32x4([f32; 4]);

    /// A lane mask of [`F32x8`] comparisons.
    #[derive(Clone, Copy, Debug)]
    pub struct M8(u32);

    /// A lane mask of [`F32x4`] comparisons.
    #[derive(Clone, Copy, Debug)]
    pub struct M4(u32);

    #[inline(always)]
    fn min(a: f32, b: f32) -> f32 {
        if a < b { a } else { b }
    }

    #[inline(always)]
    fn max(a: f32, b: f32) -> f32 {
        if a > b { a } else { b }
    }

    macro_rules! lanes {
        ($t:ident, $n:expr) => {
            impl $t {
                #[inline(always)]
                pub fn load(a: &[f32; $n]) -> $t {
                    $t(*a)
                }
                #[inline(always)]
                pub fn splat(x: f32) -> $t {
                    $t([x; $n])
                }
                #[inline(always)]
                pub fn store(self, out: &mut [f32; $n]) {
                    *out = self.0;
                }
                #[inline(always)]
                pub fn mul_add(self, b: $t, c: $t) -> $t {
                    $t(std::array::from_fn(|i| self.0[i].mul_add(b.0[i], c.0[i])))
                }
                #[inline(always)]
                pub fn mul(self, b: $t) -> $t {
                    $t(std::array::from_fn(|i| self.0[i] * b.0[i]))
                }
                #[inline(always)]
                pub fn zero() -> $t {
                    $t([0.0; $n])
                }
                #[inline(always)]
                pub fn neg_mul_add(self, b: $t, c: $t) -> $t {
                    $t(std::array::from_fn(|i| {
                        (-self.0[i]).mul_add(b.0[i], c.0[i])
                    }))
                }
                #[inline(always)]
                pub fn signs_differ(self, b: $t, c: $t) -> u32 {
                    (0..$n)
                        .map(|i| {
                            let (x, y, z) =
                                (self.0[i].to_bits(), b.0[i].to_bits(), c.0[i].to_bits());
                            (((x ^ y) | (x ^ z)) >> 31) << i
                        })
                        .fold(0, |m, b| m | b)
                }
                #[inline(always)]
                pub fn xor_sign(self, sign: $t) -> $t {
                    $t(std::array::from_fn(|i| {
                        f32::from_bits(self.0[i].to_bits() ^ (sign.0[i].to_bits() & 0x8000_0000))
                    }))
                }
            }
        };
    }
    lanes!(F32x8, 8);
    lanes!(F32x4, 4);

    impl F32x8 {
        #[inline(always)]
        pub fn min(self, b: F32x8) -> F32x8 {
            F32x8(std::array::from_fn(|i| min(self.0[i], b.0[i])))
        }
        #[inline(always)]
        pub fn max(self, b: F32x8) -> F32x8 {
            F32x8(std::array::from_fn(|i| max(self.0[i], b.0[i])))
        }
        #[inline(always)]
        fn cmp(self, b: F32x8, f: impl Fn(f32, f32) -> bool) -> M8 {
            M8((0..8).fold(0, |m, i| m | ((f(self.0[i], b.0[i]) as u32) << i)))
        }
        #[inline(always)]
        fn zip_bits(self, b: F32x8, f: impl Fn(i32, i32) -> i32) -> F32x8 {
            F32x8(std::array::from_fn(|i| {
                f32::from_bits(f(self.0[i].to_bits() as i32, b.0[i].to_bits() as i32) as u32)
            }))
        }
        #[inline(always)]
        pub fn max_bits(self, b: F32x8) -> F32x8 {
            self.zip_bits(b, i32::max)
        }
        #[inline(always)]
        pub fn min_bits(self, b: F32x8) -> F32x8 {
            self.zip_bits(b, i32::min)
        }
        #[inline(always)]
        pub fn less_ulps(self, ulps: i32) -> F32x8 {
            self.map(|x| super::widen_ulps(x, -ulps))
        }
        #[inline(always)]
        pub fn below_bits(self, b: F32x8) -> M8 {
            self.cmp(b, super::below_bits)
        }
        #[inline(always)]
        fn map(self, f: impl Fn(f32) -> f32) -> F32x8 {
            F32x8(std::array::from_fn(|i| f(self.0[i])))
        }
        #[inline(always)]
        fn zip(self, b: F32x8, f: impl Fn(f32, f32) -> f32) -> F32x8 {
            F32x8(std::array::from_fn(|i| f(self.0[i], b.0[i])))
        }
        #[inline(always)]
        pub fn le(self, b: F32x8) -> M8 {
            self.cmp(b, |x, y| x <= y)
        }
        #[inline(always)]
        pub fn lt(self, b: F32x8) -> M8 {
            self.cmp(b, |x, y| x < y)
        }
        #[inline(always)]
        pub fn gt(self, b: F32x8) -> M8 {
            self.cmp(b, |x, y| x > y)
        }
        #[inline(always)]
        pub fn eq(self, b: F32x8) -> M8 {
            self.cmp(b, |x, y| x == y)
        }
        #[inline(always)]
        pub fn ne(self, b: F32x8) -> M8 {
            self.cmp(b, |x, y| x != y)
        }
        /// Lanes 0 to 3 from `lo`, 4 to 7 from `hi`.
        #[inline(always)]
        pub fn load_halves(lo: &[f32; 4], hi: &[f32; 4]) -> F32x8 {
            F32x8(std::array::from_fn(
                |i| if i < 4 { lo[i] } else { hi[i - 4] },
            ))
        }
        #[inline(always)]
        pub fn add(self, b: F32x8) -> F32x8 {
            self.zip(b, |x, y| x + y)
        }
        #[inline(always)]
        pub fn sub(self, b: F32x8) -> F32x8 {
            self.zip(b, |x, y| x - y)
        }
        #[inline(always)]
        pub fn div(self, b: F32x8) -> F32x8 {
            self.zip(b, |x, y| x / y)
        }
        #[inline(always)]
        pub fn sqrt(self) -> F32x8 {
            self.map(f32::sqrt)
        }
        #[inline(always)]
        pub fn abs(self) -> F32x8 {
            self.map(f32::abs)
        }
        #[inline(always)]
        pub fn neg(self) -> F32x8 {
            self.map(|x| -x)
        }
        #[inline(always)]
        pub fn one_with_sign_of(self) -> F32x8 {
            self.map(|x| 1.0f32.copysign(x))
        }
        #[inline(always)]
        pub fn is_finite(self) -> M8 {
            M8((0..8).fold(0, |m, i| m | ((self.0[i].is_finite() as u32) << i)))
        }
    }

    impl M8 {
        #[inline(always)]
        pub fn bits(self) -> u32 {
            self.0
        }
        #[inline(always)]
        pub fn and(self, b: M8) -> M8 {
            M8(self.0 & b.0)
        }
        #[inline(always)]
        pub fn or(self, b: M8) -> M8 {
            M8(self.0 | b.0)
        }
        #[inline(always)]
        pub fn not(self) -> M8 {
            M8(!self.0 & 0xff)
        }
        #[inline(always)]
        pub fn select(self, a: F32x8, b: F32x8) -> F32x8 {
            F32x8(std::array::from_fn(|i| {
                if self.0 >> i & 1 != 0 { a.0[i] } else { b.0[i] }
            }))
        }
    }

    impl F32x4 {
        #[inline(always)]
        pub fn add(self, b: F32x4) -> F32x4 {
            F32x4(std::array::from_fn(|i| self.0[i] + b.0[i]))
        }
        #[inline(always)]
        pub fn sub(self, b: F32x4) -> F32x4 {
            F32x4(std::array::from_fn(|i| self.0[i] - b.0[i]))
        }
        #[inline(always)]
        pub fn div(self, b: F32x4) -> F32x4 {
            F32x4(std::array::from_fn(|i| self.0[i] / b.0[i]))
        }
        #[inline(always)]
        pub fn abs(self) -> F32x4 {
            F32x4(std::array::from_fn(|i| self.0[i].abs()))
        }
        #[inline(always)]
        pub fn max(self, b: F32x4) -> F32x4 {
            F32x4(std::array::from_fn(|i| max(self.0[i], b.0[i])))
        }
        #[inline(always)]
        fn cmp(self, b: F32x4, f: impl Fn(f32, f32) -> bool) -> M4 {
            M4((0..4).fold(0, |m, i| m | ((f(self.0[i], b.0[i]) as u32) << i)))
        }
        #[inline(always)]
        pub fn lt(self, b: F32x4) -> M4 {
            self.cmp(b, |x, y| x < y)
        }
        #[inline(always)]
        pub fn gt(self, b: F32x4) -> M4 {
            self.cmp(b, |x, y| x > y)
        }
        #[inline(always)]
        pub fn eq(self, b: F32x4) -> M4 {
            self.cmp(b, |x, y| x == y)
        }
        #[inline(always)]
        pub fn ne(self, b: F32x4) -> M4 {
            self.cmp(b, |x, y| x != y)
        }
    }

    impl M4 {
        #[inline(always)]
        pub fn bits(self) -> u32 {
            self.0
        }
        #[inline(always)]
        pub fn and(self, b: M4) -> M4 {
            M4(self.0 & b.0)
        }
        #[inline(always)]
        pub fn or(self, b: M4) -> M4 {
            M4(self.0 | b.0)
        }
        #[inline(always)]
        pub fn not(self) -> M4 {
            M4(!self.0 & 0xf)
        }
    }

    /// Eight `u32` lanes, with wrapping arithmetic.
    #[derive(Clone, Copy, Debug)]
    pub struct U32x8([u32; 8]);

    impl U32x8 {
        #[inline(always)]
        pub fn load(a: &[u32; 8]) -> U32x8 {
            U32x8(*a)
        }
        #[inline(always)]
        pub fn splat(x: u32) -> U32x8 {
            U32x8([x; 8])
        }
        #[inline(always)]
        pub fn store(self, out: &mut [u32; 8]) {
            *out = self.0;
        }
        #[inline(always)]
        pub fn wrapping_add(self, b: U32x8) -> U32x8 {
            U32x8(std::array::from_fn(|i| self.0[i].wrapping_add(b.0[i])))
        }
        #[inline(always)]
        pub fn wrapping_mul(self, b: U32x8) -> U32x8 {
            U32x8(std::array::from_fn(|i| self.0[i].wrapping_mul(b.0[i])))
        }
        #[inline(always)]
        pub fn xor(self, b: U32x8) -> U32x8 {
            U32x8(std::array::from_fn(|i| self.0[i] ^ b.0[i]))
        }
        #[inline(always)]
        pub fn shr<const N: i32>(self) -> U32x8 {
            U32x8(self.0.map(|x| x >> N))
        }
        #[inline(always)]
        pub fn reverse_bits(self) -> U32x8 {
            U32x8(self.0.map(u32::reverse_bits))
        }
        #[inline(always)]
        pub fn lookup(self, table: &[u32; 256]) -> U32x8 {
            U32x8(self.0.map(|x| table[(x & 255) as usize]))
        }
        #[inline(always)]
        pub fn unit(self) -> [f32; 8] {
            self.0
                .map(|x| (x >> 8) as f32 * (1.0 / (1u32 << 24) as f32))
        }
    }
}

pub use imp::{F32x4, F32x8, M4, M8, U32x8};

/// The operations of the watertight triangle test, for four lanes (one block of triangles) and
/// eight (two blocks tested at once): the test is written once against this, and each width
/// runs it as the inherent methods above (one instruction an operation with AVX2).
pub trait TriLanes: Copy {
    type Mask: LaneMask;
    fn splat(x: f32) -> Self;
    fn zero() -> Self;
    fn add(self, b: Self) -> Self;
    fn sub(self, b: Self) -> Self;
    fn mul(self, b: Self) -> Self;
    fn div(self, b: Self) -> Self;
    /// `self * b + c`, rounded once.
    fn mul_add(self, b: Self, c: Self) -> Self;
    /// `c - self * b`, rounded once.
    fn neg_mul_add(self, b: Self, c: Self) -> Self;
    /// Bit i set when lanes i of `self`, `b` and `c` do not all have the same sign bit.
    fn signs_differ(self, b: Self, c: Self) -> u32;
    /// The lanes with their sign bit flipped where `sign` has it set.
    fn xor_sign(self, sign: Self) -> Self;
    fn abs(self) -> Self;
    fn max(self, b: Self) -> Self;
    fn lt(self, b: Self) -> Self::Mask;
    fn gt(self, b: Self) -> Self::Mask;
    fn eq(self, b: Self) -> Self::Mask;
    fn ne(self, b: Self) -> Self::Mask;
    /// The lanes as an array (each written, none zeroed first).
    type Array: Copy + std::ops::Index<usize, Output = f32> + std::ops::IndexMut<usize>;
    fn to_array(self) -> Self::Array;
}

/// A [`TriLanes`] comparison's mask.
pub trait LaneMask: Copy {
    fn bits(self) -> u32;
    fn and(self, b: Self) -> Self;
    fn or(self, b: Self) -> Self;
    fn not(self) -> Self;
}

macro_rules! tri_lanes {
    ($t:ident, $m:ident) => {
        impl TriLanes for $t {
            type Mask = $m;
            #[inline(always)]
            fn splat(x: f32) -> $t {
                $t::splat(x)
            }
            #[inline(always)]
            fn zero() -> $t {
                $t::zero()
            }
            #[inline(always)]
            fn add(self, b: $t) -> $t {
                $t::add(self, b)
            }
            #[inline(always)]
            fn sub(self, b: $t) -> $t {
                $t::sub(self, b)
            }
            #[inline(always)]
            fn mul(self, b: $t) -> $t {
                $t::mul(self, b)
            }
            #[inline(always)]
            fn div(self, b: $t) -> $t {
                $t::div(self, b)
            }
            #[inline(always)]
            fn mul_add(self, b: $t, c: $t) -> $t {
                $t::mul_add(self, b, c)
            }
            #[inline(always)]
            fn neg_mul_add(self, b: $t, c: $t) -> $t {
                $t::neg_mul_add(self, b, c)
            }
            #[inline(always)]
            fn signs_differ(self, b: $t, c: $t) -> u32 {
                $t::signs_differ(self, b, c)
            }
            #[inline(always)]
            fn xor_sign(self, sign: $t) -> $t {
                $t::xor_sign(self, sign)
            }
            #[inline(always)]
            fn abs(self) -> $t {
                $t::abs(self)
            }
            #[inline(always)]
            fn max(self, b: $t) -> $t {
                $t::max(self, b)
            }
            #[inline(always)]
            fn lt(self, b: $t) -> $m {
                $t::lt(self, b)
            }
            #[inline(always)]
            fn gt(self, b: $t) -> $m {
                $t::gt(self, b)
            }
            #[inline(always)]
            fn eq(self, b: $t) -> $m {
                $t::eq(self, b)
            }
            #[inline(always)]
            fn ne(self, b: $t) -> $m {
                $t::ne(self, b)
            }
            type Array = [f32; size_of::<$t>() / 4];
            #[inline(always)]
            fn to_array(self) -> Self::Array {
                let mut a = [0.0; size_of::<$t>() / 4];
                self.store(&mut a);
                a
            }
        }

        impl LaneMask for $m {
            #[inline(always)]
            fn bits(self) -> u32 {
                $m::bits(self)
            }
            #[inline(always)]
            fn and(self, b: $m) -> $m {
                $m::and(self, b)
            }
            #[inline(always)]
            fn or(self, b: $m) -> $m {
                $m::or(self, b)
            }
            #[inline(always)]
            fn not(self) -> $m {
                $m::not(self)
            }
        }
    };
}
tri_lanes!(F32x4, M4);
tri_lanes!(F32x8, M8);

/// `far` moved `ulps` units in the last place up, read as a signed integer and moved back
/// (for `far` not negative; a negative `far` stays negative, below every distance).
#[inline(always)]
pub fn widen_ulps(far: f32, ulps: i32) -> f32 {
    f32::from_bits((far.to_bits() as i32).wrapping_add(ulps) as u32)
}

/// One lane of [`F32x8::below_bits`]: whether `a`'s bit pattern is below `b`'s, as signed
/// integers (`a < b` where `a` is not negative; never where `b` is negative).
#[inline(always)]
pub fn below_bits(a: f32, b: f32) -> bool {
    (a.to_bits() as i32) < b.to_bits() as i32
}

/// Made first in a function whose 8-lane values spill to its stack frame (the ray queries,
/// the diffuse wave's shading): it makes the compiler realign the frame to a cache line, and
/// in a realigned frame each 32-byte spill slot is 32-byte aligned.
///
/// Without it the frame is only as aligned as the ABI promises (16 bytes), and where a spill
/// slot lands in a cache line depends on the callers' frames. A 32-byte slot at 48 bytes into
/// a line straddles two lines, and every load of it (a ray constant, once per node tested)
/// costs a split access. So the same query ran at two speeds: a render node, reached through
/// other callers than one process, spent 7% more time on the Cornell box (`perf`: 3,415
/// against 3,180 samples of one thread at 64 spp; with this, 3,168 against 3,232), its hottest
/// instructions the loads of the box test's constants.
#[repr(C, align(64))]
pub struct AlignedFrame(std::mem::MaybeUninit<[u8; 64]>);

impl AlignedFrame {
    #[inline(always)]
    pub fn new() -> AlignedFrame {
        let frame = AlignedFrame(std::mem::MaybeUninit::uninit());
        // Its address must be taken for it to need a place in the frame; nothing reads it.
        std::hint::black_box(&frame);
        frame
    }
}

impl Default for AlignedFrame {
    #[inline(always)]
    fn default() -> AlignedFrame {
        AlignedFrame::new()
    }
}

#[cfg(test)]
mod tests {
    use super::{F32x8, U32x8, below_bits, widen_ulps};
    use proptest::prelude::*;

    /// The comparison the walk makes of an entry distance `a` with `tmax` (`far`): `a`'s bit
    /// pattern at most `ulps` above `far`'s, as signed integers.
    fn within_ulps(a: f32, far: f32, ulps: i32) -> bool {
        below_bits(a, widen_ulps(far, ulps + 1))
    }

    /// Any `f32` but NaN, the infinities and both zeros included.
    fn number() -> impl Strategy<Value = f32> {
        prop_oneof![
            any::<f32>().prop_filter("not NaN", |x| !x.is_nan()),
            Just(0.0f32),
            Just(-0.0f32),
            Just(f32::INFINITY),
            Just(f32::NEG_INFINITY),
        ]
    }

    proptest! {
        /// The integer forms give the float answers the box test relies on: the maximum
        /// where it is not negative, the minimum where both are not negative (negative where
        /// one is), and `a <= f` with `f` widened by six units in the last place at least as
        /// far as `f * (1 + 3 * EPSILON)` reaches, never where `f` is negative.
        #[test]
        fn bit_pattern_order_is_float_order(a in number(), b in number()) {
            let lane = |x: F32x8| {
                let mut o = [0.0; 8];
                x.store(&mut o);
                o[3]
            };
            let (va, vb) = (F32x8::splat(a), F32x8::splat(b));
            let max = lane(va.max_bits(vb));
            if a.max(b) > 0.0 {
                prop_assert_eq!(max.to_bits(), a.max(b).to_bits());
            } else if a.to_bits() == 0 || b.to_bits() == 0 {
                prop_assert_eq!(max.to_bits(), 0);
            }
            let min = lane(va.min_bits(vb));
            if a.is_sign_positive() && b.is_sign_positive() {
                prop_assert_eq!(min.to_bits(), a.min(b).to_bits());
            } else {
                prop_assert!(min.is_sign_negative());
            }
            let below = va.below_bits(vb).bits() == 0xff;
            if a.is_sign_positive() {
                prop_assert_eq!(below, b.is_sign_positive() && a < b);
                let within = within_ulps(a, b, 6);
                if a <= b * (1.0 + 3.0 * f32::EPSILON) && b.is_sign_positive() {
                    prop_assert!(within);
                }
                if b.is_sign_negative() {
                    prop_assert!(!within);
                }
                if within {
                    prop_assert!(a <= b * (1.0 + 8.0 * f32::EPSILON) || a <= b + f32::from_bits(6));
                }
            }
        }
    }

    /// The integer lanes give what `u32`'s own operations give, lane by lane.
    #[test]
    fn u32_lanes_agree_with_scalar_operations() {
        let a = [
            0,
            1,
            0x8000_0000,
            u32::MAX,
            0x1234_5678,
            0xdead_beef,
            255,
            0x00ff_ff00,
        ];
        let b = [
            7,
            u32::MAX,
            3,
            2,
            0x9e37_79b9,
            0x0101_0101,
            0x8000_0001,
            12345,
        ];
        let out = |x: U32x8| {
            let mut o = [0; 8];
            x.store(&mut o);
            o
        };
        let (va, vb) = (U32x8::load(&a), U32x8::load(&b));
        let table: [u32; 256] = std::array::from_fn(|i| (i as u32).wrapping_mul(0x0100_0193));
        for i in 0..8 {
            assert_eq!(out(va.wrapping_add(vb))[i], a[i].wrapping_add(b[i]));
            assert_eq!(out(va.wrapping_mul(vb))[i], a[i].wrapping_mul(b[i]));
            assert_eq!(out(va.xor(vb))[i], a[i] ^ b[i]);
            assert_eq!(out(va.shr::<8>())[i], a[i] >> 8);
            assert_eq!(out(va.reverse_bits())[i], a[i].reverse_bits());
            assert_eq!(out(va.lookup(&table))[i], table[(a[i] & 255) as usize]);
            let unit = (a[i] >> 8) as f32 * (1.0 / (1u32 << 24) as f32);
            assert_eq!(va.unit()[i].to_bits(), unit.to_bits());
        }
        assert_eq!(out(U32x8::splat(9)), [9; 8]);
    }
}
