//! The median the robust fits trim by.

/// The upper median of `values` (the middle one, or the upper of the two middle ones), 0
/// for none: a selection, not a sort, since the fits call it per edge and per frame pair.
pub fn median(mut values: Vec<f64>) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    let mid = values.len() / 2;
    *values.select_nth_unstable_by(mid, f64::total_cmp).1
}

#[cfg(test)]
mod tests {
    use super::median;

    #[test]
    fn upper_median_and_zero_for_none() {
        assert_eq!(median(vec![]), 0.0);
        assert_eq!(median(vec![3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(vec![4.0, 1.0, 3.0, 2.0]), 3.0);
    }
}
