//! The in-memory order of queued jobs: priority classes, FIFO (by admission sequence)
//! within a class. The persistent truth is the job records; this is rebuilt from them at
//! startup.
//!
//! Locking: plain data inside the core's `State`, read and changed under its lock only.

use std::collections::BTreeMap;

use super::record::Priority;

#[derive(Default)]
pub struct Queue {
    entries: BTreeMap<(u8, u64), String>,
    depth: [usize; 3],
}

impl Queue {
    pub fn push(&mut self, priority: Priority, seq: u64, id: String) {
        if self.entries.insert((priority.rank(), seq), id).is_none() {
            self.depth[priority.rank() as usize] += 1;
        }
    }

    pub fn remove(&mut self, priority: Priority, seq: u64) -> bool {
        let removed = self.entries.remove(&(priority.rank(), seq)).is_some();
        if removed {
            self.depth[priority.rank() as usize] -= 1;
        }
        removed
    }

    /// The next job: the oldest of the highest non-empty class.
    pub fn pop(&mut self) -> Option<String> {
        let ((rank, _), id) = self.entries.pop_first()?;
        self.depth[rank as usize] -= 1;
        Some(id)
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    pub fn depth(&self, priority: Priority) -> usize {
        self.depth[priority.rank() as usize]
    }

    /// 1-based position of a queued job (how many jobs run before it, plus one).
    pub fn position(&self, priority: Priority, seq: u64) -> u64 {
        self.entries.range(..(priority.rank(), seq)).count() as u64 + 1
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn priority_classes_then_fifo() {
        let mut q = Queue::default();
        q.push(Priority::Low, 1, "a".into());
        q.push(Priority::Normal, 2, "b".into());
        q.push(Priority::High, 3, "c".into());
        q.push(Priority::Normal, 4, "d".into());
        q.push(Priority::High, 5, "e".into());
        assert_eq!(q.position(Priority::Low, 1), 5);
        assert_eq!(q.position(Priority::Normal, 4), 4);
        assert_eq!(q.depth(Priority::High), 2);
        assert!(q.remove(Priority::Normal, 2));
        let order: Vec<String> = std::iter::from_fn(|| q.pop()).collect();
        assert_eq!(order, ["c", "e", "d", "a"]);
        assert_eq!(q.depth(Priority::High) + q.depth(Priority::Normal) + q.depth(Priority::Low), 0);
    }
}
