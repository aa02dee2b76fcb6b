"""
YAML and JSON read as plain data, within bounds: the one loader of the files the package reads.

Every YAML the package reads (result files, other tools' samples) is data, never objects:
`load` builds only mappings, lists, strings and numbers (yaml's safe loader).  A hostile or
broken file cannot take the machine: the text may hold at most MAX_CHARACTERS, no aliases
(`*name`: the "billion laughs" of a few lines that expand to gigabytes; none of the files read
here needs one) and at most MAX_DEPTH levels of nesting; an integer may have at most
MAX_INT_DIGITS digits.  `load_json` applies the same bounds to JSON.  Every failure is a
BadInputError that names the file and, where known, the line.
"""

import functools
import json

from quatcal_ros.core.units import shown
from quatcal_ros.files.text_input import BadInputError, read_text

MAX_CHARACTERS = 64 * 1024 * 1024   # far above any samples or result file (a sample: ~400 B)
MAX_DEPTH = 64                    # a samples file nests 5 levels
MAX_INT_DIGITS = 100              # no count, stamp or coordinate needs more


@functools.lru_cache(maxsize=None)
def _loader():
    """Return the bounded loader class (made on first use: PyYAML is imported only then)."""
    import yaml

    class _BoundedLoader(yaml.SafeLoader):
        """The safe loader, refusing aliases and deep nesting while it composes a document."""

        def compose_node(self, parent, index):
            if self.check_event(yaml.events.AliasEvent):
                event = self.peek_event()
                raise yaml.composer.ComposerError(
                    None, None, f'an alias (*{event.anchor}): aliases are not accepted in a '
                                'data file', event.start_mark)
            self._depth = getattr(self, '_depth', 0) + 1
            try:
                if self._depth > MAX_DEPTH:
                    raise yaml.composer.ComposerError(
                        None, None, f'nested deeper than {MAX_DEPTH} levels',
                        self.peek_event().start_mark)
                return super().compose_node(parent, index)
            finally:
                self._depth -= 1

        def construct_yaml_int(self, node):
            """Return the integer of `node`; ValueError for one with too many digits."""
            digits = len(str(node.value).lstrip('+-').replace('_', ''))
            if digits > MAX_INT_DIGITS:
                raise ValueError(f'line {node.start_mark.line + 1}: an integer of {digits} '
                                 f'digits (at most {MAX_INT_DIGITS})')
            return super().construct_yaml_int(node)

    _BoundedLoader.add_constructor('tag:yaml.org,2002:int',
                                   _BoundedLoader.construct_yaml_int)
    return _BoundedLoader


def load_file(path, holds='the file'):
    """Return the plain data of the YAML file `path` (load's errors, and 'cannot read')."""
    return load(read_text(path, MAX_CHARACTERS), str(path), holds)


def load(text, name, holds='the file'):
    """
    Return the plain data of YAML `text` read from `name`.

    :param holds: what the file is, for the message ('a samples file', 'a result file').
    :raises BadInputError: 'NAME, line L: refused: not plain data (...)' for a YAML tag that
        asks for an object, 'NAME, line L: not readable YAML: ...' for bad syntax, an alias,
        deep nesting, or an integer with too many digits; 'NAME: larger than ...' for size.
    """
    _check_size(text, name)
    loader = None
    try:
        loader = _loader()(text)   # yaml.safe_load's loader, bounded (class docstring)
        return loader.get_single_data()
    except _yaml().constructor.ConstructorError as error:
        raise BadInputError(f'{name}{_line(error)}: refused: not plain data ({error.problem}); '
                            f'{holds} holds only mappings, lists, strings and numbers') from None
    except _yaml().YAMLError as error:
        problem = getattr(error, 'problem', None) or str(error).splitlines()[0]
        raise BadInputError(f'{name}{_line(error)}: not readable YAML: {problem}') from None
    except (ValueError, RecursionError) as error:   # int() of a 5000-digit number, ...
        raise BadInputError(f'{name}: not readable YAML: {shown(error, 200)}') from None
    finally:
        if loader is not None:
            loader.dispose()


def dump(document, **options):
    """
    Return `document` as YAML text (PyYAML's safe_dump with `options`): the one writer.

    Text of several lines (a URDF joint) is written as a literal block, as it reads and is
    pasted, where YAML allows one (else quoted, as safe_dump does); text beyond ASCII (a frame
    named in the user's language) as itself, not as escapes: the files are UTF-8.
    """
    return _yaml().dump(document, Dumper=_block_text_dumper(), allow_unicode=True, **options)


@functools.lru_cache(maxsize=None)
def _block_text_dumper():
    yaml = _yaml()

    class BlockTextDumper(yaml.SafeDumper):
        pass

    def text(dumper, value):
        style = '|' if '\n' in value else None
        return dumper.represent_scalar('tag:yaml.org,2002:str', value, style=style)
    BlockTextDumper.add_representer(str, text)
    return BlockTextDumper


def _yaml():
    import yaml   # on first use: `solve` of a CSV, the node's message path never need it
    return yaml


def load_json(text, name):
    """Return the plain data of JSON `text` read from `name`, within the module's bounds."""
    _check_size(text, name)
    try:
        return json.loads(text, parse_int=_bounded_int)
    except RecursionError:
        raise BadInputError(f'{name}: not readable JSON: nested too deeply') from None
    except ValueError as error:
        line = getattr(error, 'lineno', None)
        where = f', line {line}' if line else ''
        raise BadInputError(f'{name}{where}: not readable JSON: '
                            f'{getattr(error, "msg", None) or shown(error, 200)}') from None


def _bounded_int(text):
    if len(text.lstrip('-')) > MAX_INT_DIGITS:
        raise ValueError(f'an integer of {len(text)} digits (at most {MAX_INT_DIGITS})')
    return int(text)


def _check_size(text, name):
    if len(text) > MAX_CHARACTERS:
        raise BadInputError(f'{name}: larger than {MAX_CHARACTERS // (1024 * 1024)} MiB: not a '
                            'samples or result file')


def _line(error):
    mark = getattr(error, 'problem_mark', None)
    return f', line {mark.line + 1}' if mark is not None else ''
