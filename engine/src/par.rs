//! Parallel loops whose body is a trait object.
//!
//! Rayon compiles its splitting, joining and job code once per closure type: every
//! `.for_each(|..| ..)` or `.map(|..| ..)` in a parallel chain is a new copy, about 3 000 lines of
//! LLVM IR before optimisation. Passed as `&dyn Fn`, a body of a given item type shares one copy
//! with every other loop of that iterator type. The cost is one indirect call per item, which is
//! nothing next to a row, a band or a chunk of work; loops over single pixels should keep a plain
//! closure.
//!
//! The results are those of the plain `for_each`/`map`: the same items reach the same body, in
//! the same chunks.

use rayon::iter::{Map, ParallelIterator};

/// `for_each_dyn`, `map_dyn` and `for_each_init_dyn`: rayon's loops with the body behind a
/// `&dyn Fn`.
pub trait ParallelIteratorDyn: ParallelIterator {
    /// [`ParallelIterator::for_each`] with the body as a trait object.
    fn for_each_dyn(self, op: &(dyn Fn(Self::Item) + Sync)) {
        self.for_each(op);
    }

    /// [`ParallelIterator::map`] with the body as a trait object.
    fn map_dyn<R: Send>(
        self,
        op: &(dyn Fn(Self::Item) -> R + Sync),
    ) -> Map<Self, &(dyn Fn(Self::Item) -> R + Sync)> {
        self.map(op)
    }

    /// [`ParallelIterator::for_each_init`] with the initialiser and the body as trait objects.
    fn for_each_init_dyn<T>(
        self,
        init: &(dyn Fn() -> T + Sync),
        op: &(dyn Fn(&mut T, Self::Item) + Sync),
    ) {
        self.for_each_init(init, op);
    }
}

impl<I: ParallelIterator> ParallelIteratorDyn for I {}

#[cfg(test)]
mod tests {
    use super::*;
    use rayon::prelude::*;

    #[test]
    fn map_dyn_collects_what_map_collects() {
        let values: Vec<u64> = (0..10_000u64).collect();
        let plain: Vec<u64> = values.par_iter().map(|v| v * v + 1).collect();
        let boxed: Vec<u64> = values.par_iter().map_dyn(&|v| v * v + 1).collect();
        assert_eq!(plain, boxed);
    }

    #[test]
    fn for_each_dyn_visits_every_chunk_once_with_its_index() {
        let mut data = vec![0u32; 1_003];
        data.par_chunks_mut(10)
            .enumerate()
            .for_each_dyn(&|(chunk_index, chunk)| {
                for (k, value) in chunk.iter_mut().enumerate() {
                    *value += (chunk_index * 10 + k) as u32;
                }
            });
        assert!(data.iter().enumerate().all(|(i, &v)| v == i as u32));
    }

    #[test]
    fn for_each_init_dyn_gives_each_chunk_a_scratch_buffer() {
        let mut data = vec![0u32; 1_003];
        data.par_chunks_mut(7).enumerate().for_each_init_dyn(
            &Vec::new,
            &|scratch: &mut Vec<u32>, (chunk_index, chunk)| {
                scratch.clear();
                scratch.extend((0..chunk.len()).map(|k| (chunk_index * 7 + k) as u32));
                chunk.copy_from_slice(scratch);
            },
        );
        assert!(data.iter().enumerate().all(|(i, &v)| v == i as u32));
    }
}
