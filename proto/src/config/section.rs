//! Sections that a crate outside the contract owns and reads alone (`[reproduce]`, read by
//! `uavmeta_reproduce`). [`Config`](super::Config) keeps such a section as the file wrote it, so
//! the contract need not know its keys; its owner declares a [`Section`] with its defaults and
//! rules on the fields, as the contract's own sections do, and reads it with
//! [`OwnedSection::read`], which refuses an unknown key, a wrong type or a broken rule with the
//! same error, naming the file, the key, the value and what was expected.

use garde::Validate;
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

use super::rules::{first_broken, Broken};
use super::ConfigError;

/// A section its owning crate declares: its key in the file, its defaults (`Default`), its rules
/// (garde). Checks that compare it with other sections are its owner's too.
pub trait Section: Serialize + DeserializeOwned + Default + Validate<Context = ()> {
    /// The table's name in the file: `reproduce` for `[reproduce]`.
    const KEY: &'static str;
}

/// A section as the file wrote it (empty when the file has none): what [`Config`](super::Config)
/// holds for a section another crate owns.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(transparent)]
pub struct OwnedSection(toml::Table);

impl OwnedSection {
    /// The section as its owner declares it, every key it leaves out at its default; `origin` is
    /// the config's, for errors.
    pub fn read<S: Section>(&self, origin: &str) -> Result<S, ConfigError> {
        let section = S::deserialize(self.0.clone()).map_err(|e| ConfigError::Parse {
            origin: origin.to_string(),
            message: format!(
                "[{}]: {}",
                S::KEY,
                e.to_string().trim_end().replace('\n', " ")
            ),
        })?;
        section.validate().map_err(|report| {
            let broken = first_broken(report);
            Broken {
                key: format!("{}.{}", S::KEY, broken.key),
                ..broken
            }
            .at(origin)
        })?;
        Ok(section)
    }

    /// `section` with every key written out, as a config saves it.
    pub fn of<S: Section>(section: &S) -> Self {
        let table = toml::Table::try_from(section).expect("a section always serialises to a table");
        Self(table)
    }

    /// Whether the file left the section out.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
}
