"""
Command-line options of `solve` and `replay`, made from the settings table.

Each setting whose row names the tool (Setting.tools) becomes an option: `--still-window-s`
for still_window_s, with the table's description, default, unit and range.  A value outside
the range, or not one of the choices, is refused by argparse (exit 2, the option named).  A few
options keep the names users know (OPTION_NAMES).  `settings_of(args)` turns the parsed
options into the checked stream.settings.Settings the session is made from.
"""

import argparse
import re
import textwrap

from quatcal_ros.core.units import plain_number
from quatcal_ros.stream.settings import DEFAULTS, SETTINGS, Settings

# Options named otherwise than their setting (the command-line contract).
OPTION_NAMES = {'capture_mode': '--capture', 'sensor_time_offset_s': '--sensor-time-offset',
                'robust': '--no-robust', 'invert_sensor': '--invert-sensor'}
# Choices offered offline where the node has more (no one calls ~/capture on a bag).
OFFLINE_CHOICES = {'capture_mode': ('auto', 'continuous')}
# Extra words for options whose offline meaning adds to the node's.
OFFLINE_HELP = {
    'capture_mode': 'offline, auto falls back to continuous when the whole bag has no stop '
                    '(see --no-fallback)',
    'robust': 'plain least squares: no outlier screening or rejection',
    'invert_sensor': 'the sensor poses are the sensor in the object frame (the inverse of '
                     'the usual detector output)',
}


class HelpFormatter(argparse.HelpFormatter):
    """argparse's help, whose lines never break inside an --option-name at its hyphens."""

    def _split_lines(self, text, width):
        return textwrap.wrap(' '.join(text.split()), width, break_on_hyphens=False)


def option_name(setting):
    """Return the command-line option of `setting`, e.g. --still-window-s."""
    return OPTION_NAMES.get(setting.name, '--' + setting.name.replace('_', '-'))


def add_setting_options(parser, tool, names=None):
    """
    Add the options of the settings offered by `tool` ('solve' or 'replay') to `parser`.

    names: only these settings (default: all the tool offers).  The destination of each
    option is the setting's name.
    """
    for setting in SETTINGS:
        if tool not in setting.tools or (names is not None and setting.name not in names):
            continue
        flag = option_name(setting)
        words = [_as_options(setting.description.rstrip('.'), tool)]
        if isinstance(setting.default, bool):
            words = [OFFLINE_HELP.get(setting.name, words[0])]
        elif setting.name in OFFLINE_HELP:
            words.append(OFFLINE_HELP[setting.name])
        if isinstance(setting.default, bool):
            # A flag states the opposite of the default (--no-robust, --invert-sensor).
            parser.add_argument(flag, dest=setting.name, action='store_const',
                                const=not setting.default, default=setting.default,
                                help='; '.join(words))
            continue
        choices = OFFLINE_CHOICES.get(setting.name, setting.choices) or None
        if not choices:
            words.append(f'{setting.constraints}; default {setting.default!r}'.lstrip('; '))
        else:
            words.append(f'default {setting.default}')
        parser.add_argument(flag, dest=setting.name, default=setting.default,
                            choices=choices, type=None if choices else _parser_of(setting),
                            metavar=None if choices else setting.unit.upper() or 'VALUE',
                            help='; '.join(words).replace('%', '%%'))


def _as_options(text, tool):
    """Return `text` with the settings it names that `tool` offers named as its options."""
    for setting in SETTINGS:
        if '_' in setting.name and tool in setting.tools:   # (one word may be a plain word)
            text = re.sub(rf'\b{setting.name}\b', option_name(setting), text)
    return text


def _parser_of(setting):
    """Return the argparse type of `setting`: convert, then check against the table."""
    kind = type(setting.default)

    def parse(text):
        try:
            value = plain_number(text, kind) if kind is not str else text
        except ValueError:
            what = 'whole number' if kind is int else 'number'
            raise argparse.ArgumentTypeError(f'{text!r} is not a {what}') from None
        reason = setting.check(setting.plain(value))
        if reason:
            raise argparse.ArgumentTypeError(reason)
        return setting.plain(value)
    parse.__name__ = kind.__name__
    return parse


def settings_of(args, **fixed):
    """
    Return the checked Settings of parsed `args` (each setting's option, else its default).

    fixed: values that override both (e.g. the setup an imported file names).
    :raises stream.settings.ConfigError: when the core refuses the combination.
    """
    values = {name: getattr(args, name, default) for name, default in DEFAULTS.items()}
    values.update(fixed)
    return Settings.from_values(values)
