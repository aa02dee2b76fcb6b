"""
YAML read as plain data: the one safe loader of the files the package reads.

Every YAML the package reads (result files, other tools' samples) is data, never objects:
`load` uses yaml.safe_load, which builds only mappings, lists, strings and numbers, and turns
every failure into a BadInputError that names the file and the line.
"""

from quatcal_ros.files.samples_csv import BadInputError
import yaml


def load(text, name, holds='the file'):
    """
    Return the plain data of YAML `text` read from `name`.

    :param holds: what the file is, for the message ('a samples file', 'a result file').
    :raises BadInputError: 'NAME, line L: refused: not plain data (...)' for a YAML tag that
        asks for an object, 'NAME, line L: not readable YAML: ...' for bad syntax.
    """
    try:
        return yaml.safe_load(text)
    except yaml.constructor.ConstructorError as error:
        raise BadInputError(f'{name}{_line(error)}: refused: not plain data ({error.problem}); '
                            f'{holds} holds only mappings, lists, strings and numbers') from None
    except yaml.YAMLError as error:
        problem = getattr(error, 'problem', None) or str(error).splitlines()[0]
        raise BadInputError(f'{name}{_line(error)}: not readable YAML: {problem}') from None


def _line(error):
    mark = getattr(error, 'problem_mark', None)
    return f', line {mark.line + 1}' if mark is not None else ''
