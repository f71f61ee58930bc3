//! Small SIMD types for the ray-casting kernel: eight and four `f32` lanes and their masks.
//!
//! With AVX2 and FMA (the default build, x86-64-v3) each operation is one instruction; on
//! other targets the same operations run lane by lane. Both give the same bits: `min`/`max`
//! follow the SSE rule (`a < b ? a : b`, which also fixes which operand a NaN yields), and
//! `mul_add` is fused in both (`f32::mul_add` is correctly rounded, like the instruction).
//! The kernel is written once against these types.

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
    }

    impl M8 {
        /// Bit i set when lane i is true.
        #[inline(always)]
        pub fn bits(self) -> u32 {
            unsafe { _mm256_movemask_ps(self.0) as u32 }
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
        pub fn le(self, b: F32x8) -> M8 {
            M8((0..8).fold(0, |m, i| m | (((self.0[i] <= b.0[i]) as u32) << i)))
        }
    }

    impl M8 {
        #[inline(always)]
        pub fn bits(self) -> u32 {
            self.0
        }
    }

    impl F32x4 {
        #[inline(always)]
        pub fn zero() -> F32x4 {
            F32x4([0.0; 4])
        }
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
        pub fn neg_mul_add(self, b: F32x4, c: F32x4) -> F32x4 {
            F32x4(std::array::from_fn(|i| {
                (-self.0[i]).mul_add(b.0[i], c.0[i])
            }))
        }
        #[inline(always)]
        pub fn xor_sign(self, sign: F32x4) -> F32x4 {
            F32x4(std::array::from_fn(|i| {
                f32::from_bits(self.0[i].to_bits() ^ (sign.0[i].to_bits() & 0x8000_0000))
            }))
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
}

pub use imp::{F32x4, F32x8, M4, M8};
