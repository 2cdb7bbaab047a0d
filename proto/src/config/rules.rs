//! The rules the config sections declare on their fields, and the error a broken one becomes.
//!
//! A section derives [`garde::Validate`] and names each field's rule in an attribute, such as
//! `#[garde(custom(finite(0.0.., "a finite number >= 0")))]`; garde walks the sections and names
//! the field that breaks one by its path (`meta.alpha`, `tasks[1].lambda`). Its own rules are not
//! used: their messages ("lower than 1") cannot be replaced, and a range lets NaN through. Its
//! errors carry a message only, so a rule writes the value and what was expected into it, and
//! [`first_broken`] reads them back. Checks that compare fields stay code and return a
//! [`Broken`] of their own.

use std::borrow::Borrow;
use std::fmt::{Debug, Display};
use std::ops::RangeBounds;

use super::ConfigError;

/// Separates the value from the expectation in a rule's message (ASCII's unit separator, which
/// neither a `Debug` value nor an expectation contains).
const SEPARATOR: char = '\u{1f}';

/// A check a config fails: the dotted key, the value (as `Debug` prints it) and what was expected.
#[derive(Debug, Clone, PartialEq)]
pub struct Broken {
    pub key: String,
    pub value: String,
    pub expected: String,
}

impl Broken {
    pub fn new(key: impl Into<String>, value: &dyn Debug, expected: impl Display) -> Self {
        Self {
            key: key.into(),
            value: format!("{value:?}"),
            expected: expected.to_string(),
        }
    }

    /// The error of the config read from `origin`.
    pub fn at(self, origin: &str) -> ConfigError {
        ConfigError::Invalid {
            origin: origin.to_string(),
            key: self.key,
            value: self.value,
            expected: self.expected,
        }
    }
}

/// The first rule a report says was broken, in the order of the sections and their fields.
pub fn first_broken(report: garde::Report) -> Broken {
    let (path, error) = report
        .into_inner()
        .into_iter()
        .next()
        .expect("garde reports at least one broken rule");
    let (value, expected) = error
        .message()
        .split_once(SEPARATOR)
        .expect("every rule writes its value and expectation");
    Broken {
        key: path.to_string(),
        value: value.to_string(),
        expected: expected.to_string(),
    }
}

/// What a rule returns: `value` passes where `ok`, or fails with `expected`.
fn check<T: Debug + ?Sized>(ok: bool, value: &T, expected: impl Display) -> garde::Result {
    match ok {
        true => Ok(()),
        false => Err(garde::Error::new(format!("{value:?}{SEPARATOR}{expected}"))),
    }
}

/// At least `min`, expecting "at least `min`".
pub fn at_least<T: PartialOrd + Debug + Display>(min: T) -> impl FnOnce(&T, &()) -> garde::Result {
    move |value, _| check(*value >= min, value, format_args!("at least {min}"))
}

/// At most `max`, expecting "at most `max`".
pub fn at_most<T: PartialOrd + Debug + Display>(max: T) -> impl FnOnce(&T, &()) -> garde::Result {
    move |value, _| check(*value <= max, value, format_args!("at most {max}"))
}

/// Inside `range`; NaN is inside none.
pub fn within<T, R>(range: R, expected: impl Display) -> impl FnOnce(&T, &()) -> garde::Result
where
    T: PartialOrd + Debug,
    R: RangeBounds<T>,
{
    move |value, _| check(range.contains(value), value, expected)
}

/// A finite number inside `range`: neither NaN nor an infinity, even where the range is open.
pub fn finite<R: RangeBounds<f64>>(
    range: R,
    expected: impl Display,
) -> impl FnOnce(&f64, &()) -> garde::Result {
    move |value, _| check(value.is_finite() && range.contains(value), value, expected)
}

/// A seed a TOML file can hold: its integers are i64.
pub fn toml_seed() -> impl FnOnce(&u64, &()) -> garde::Result {
    |value, _| {
        let most = i64::MAX as u64;
        check(*value <= most, value, format_args!("a seed at most {most}"))
    }
}

/// Something with a length: a string or a list.
pub trait Length {
    fn length(&self) -> usize;
}

impl Length for String {
    fn length(&self) -> usize {
        self.len()
    }
}

impl<T> Length for Vec<T> {
    fn length(&self) -> usize {
        self.len()
    }
}

/// Not empty.
pub fn non_empty<T: Length + Debug>(
    expected: impl Display,
) -> impl FnOnce(&T, &()) -> garde::Result {
    move |value, _| check(value.length() > 0, value, expected)
}

/// A non-empty list whose every entry is `entry`.
pub fn list_of<T: Debug>(
    entry: impl Fn(&T) -> bool,
    expected: impl Display,
) -> impl FnOnce(&Vec<T>, &()) -> garde::Result {
    move |list, _| check(!list.is_empty() && list.iter().all(entry), list, expected)
}

/// A non-empty list of layer widths, each at least 1.
pub fn widths() -> impl FnOnce(&Vec<usize>, &()) -> garde::Result {
    list_of(|&w| w >= 1, "a non-empty list of widths >= 1")
}

/// A non-empty, strictly increasing list of counts, each at least 1.
pub fn increasing(expected: impl Display) -> impl FnOnce(&Vec<usize>, &()) -> garde::Result {
    move |list, _| {
        let ok = list.first().is_some_and(|&first| first >= 1)
            && list.windows(2).all(|pair| pair[0] < pair[1]);
        check(ok, list, expected)
    }
}

/// Whatever `ok` accepts: a rule of one field's own (a device name, an endpoint); `ok` may take
/// a borrowed form of the field (`&str` for a `String`).
pub fn satisfies<T, U>(
    ok: impl FnOnce(&U) -> bool,
    expected: impl Display,
) -> impl FnOnce(&T, &()) -> garde::Result
where
    T: Borrow<U> + Debug,
    U: ?Sized,
{
    move |value, _| check(ok(value.borrow()), value, expected)
}

/// A finite number above 0.
pub fn positive(expected: impl Display) -> impl FnOnce(&f64, &()) -> garde::Result {
    move |value, _| check(value.is_finite() && *value > 0.0, value, expected)
}

/// A finite weight >= 0: an entry of `world.delta` or `planner.h_power_weights`.
pub fn is_weight(value: &f64) -> bool {
    value.is_finite() && *value >= 0.0
}
